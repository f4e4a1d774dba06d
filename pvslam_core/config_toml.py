"""A resolved config as a TOML file (``pvslam config show``): one table per section, sub-models as nested tables
(inline when short), short lists inline.  Reading the text back with :func:`pvslam_core.config.load_config` gives
the same resolved config.

TOML has no null: a key whose value is None is left out (it then loads as its default) and named in a comment
line of its table; a None where the default is not None cannot be written in TOML (``--json`` shows it).
"""
from __future__ import annotations

import json
import math
import re
from typing import Any

__all__ = ["to_toml"]

WIDTH = 100  # a sub-table whose inline form fits in this many characters is written inline
_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k: str) -> str:
    return k if _BARE.match(k) else json.dumps(k, ensure_ascii=False)


def _string(s: str) -> str:
    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def _is_leaf_table(v: Any) -> bool:
    return isinstance(v, dict) and all(not isinstance(x, dict) and x is not None and not _has_none(x)
                                       for x in v.values())


def _has_none(v: Any) -> bool:
    return v is None or (isinstance(v, (list, tuple)) and any(_has_none(x) for x in v))


def value(v: Any) -> str:
    """One TOML value (bool, int, float, str, list, table) as text."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {value(x)}" for k, x in v.items()) + " }" if v else "{}"
    raise TypeError(f"no TOML form for {type(v).__name__} {v!r}")


def _table(path: list[str], data: dict, lines: list[str]) -> None:
    body, unset, subtables = [], [], []
    for k, v in data.items():
        if _has_none(v):
            unset.append(k)
        elif isinstance(v, dict) and not (_is_leaf_table(v) and len(f"{_key(k)} = {value(v)}") <= WIDTH):
            subtables.append((k, v))
        else:
            body.append(f"{_key(k)} = {value(v)}")
    if unset:
        body.append("# not set: " + ", ".join(unset))
    if body or not subtables:
        if lines:
            lines.append("")
        lines.append("[" + ".".join(_key(p) for p in path) + "]")
        lines.extend(body)
    for k, v in subtables:
        _table(path + [k], v, lines)


def to_toml(data: dict[str, Any], header: str = "") -> str:
    """``data`` (a resolved config's ``to_dict()``: every top-level value a table) as TOML text."""
    lines: list[str] = [f"# {h}" for h in header.splitlines()] if header else []
    start = len(lines)
    for section, table in data.items():
        if not isinstance(table, dict):
            raise TypeError(f"top-level key {section!r} is not a table")
        sub: list[str] = []
        _table([section], table, sub)
        if len(lines) > start:
            lines.append("")
        lines.extend(sub)
    return "\n".join(lines) + "\n"
