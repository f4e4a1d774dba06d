"""metrics.json and other JSON outputs, written atomically.

JSON written here is strict (RFC 8259): NaN and infinities become ``null``; numpy scalars/arrays and torch
tensors become numbers/lists; tuples become lists; dict keys become strings.
"""
from __future__ import annotations

import json
import math
import os
from typing import Any

from ._atomic import atomic_write_text

__all__ = ["to_jsonable", "write_json_atomic", "read_json", "MetricsFile"]


def to_jsonable(obj: Any) -> Any:
    """A structure of plain dict/list/str/int/float/bool/None (non-finite floats -> None)."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    if hasattr(obj, "detach"):  # torch tensor
        obj = obj.detach().cpu().numpy()
    try:
        import numpy as np

        if isinstance(obj, np.ndarray):
            return to_jsonable(obj.tolist())
        if isinstance(obj, np.generic):
            return to_jsonable(obj.item())
    except ImportError:  # pragma: no cover
        pass
    if hasattr(obj, "__fspath__"):
        return os.fspath(obj)
    if hasattr(obj, "__dataclass_fields__"):
        import dataclasses

        return to_jsonable(dataclasses.asdict(obj))
    if hasattr(obj, "model_dump"):  # pydantic
        return to_jsonable(obj.model_dump())
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    """Write ``obj`` as strict JSON to ``path`` atomically (temp file in the same folder + ``os.replace``);
    ``indent=None`` writes one line with the (much faster) C encoder."""
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False) + "\n"
    atomic_write_text(path, text)


def read_json(path: str | os.PathLike) -> Any:
    with open(path, "r", encoding="utf-8") as f:
        return json.load(f)


def _deep_merge(base: dict, new: dict) -> dict:
    for k, v in new.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _deep_merge(base[k], v)
        else:
            base[k] = v
    return base


class MetricsFile:
    """A JSON object on disk that grows during a run: ``update(**kv)`` merges the given top-level keys into it
    (replacing those keys' old values; ``deep_update`` merges nested dicts recursively instead) and rewrites the
    file atomically, so it is valid whenever the run stops. An existing file is loaded and extended (a file that
    is not a JSON object is an error, not silently replaced)."""

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        self.data: dict = {}
        if os.path.exists(self.path):
            try:
                loaded = read_json(self.path)
            except json.JSONDecodeError as e:
                raise ValueError(f"{self.path}: not valid JSON ({e}); refusing to overwrite") from None
            if not isinstance(loaded, dict):
                raise ValueError(f"{self.path}: expected a JSON object, found {type(loaded).__name__}")
            self.data = loaded

    def update(self, _mapping: dict | None = None, /, **kv: Any) -> dict:
        new = to_jsonable(dict(_mapping or {}, **kv))
        data = dict(self.data)
        data.update(new)
        write_json_atomic(self.path, data)
        self.data = data
        return self.data

    def deep_update(self, _mapping: dict | None = None, /, **kv: Any) -> dict:
        new = to_jsonable(dict(_mapping or {}, **kv))
        data = _deep_merge(json.loads(json.dumps(self.data)), new)
        write_json_atomic(self.path, data)
        self.data = data
        return self.data

    def get(self, key: str, default: Any = None) -> Any:
        return self.data.get(key, default)

    def __getitem__(self, key: str) -> Any:
        return self.data[key]

    def __contains__(self, key: str) -> bool:
        return key in self.data
