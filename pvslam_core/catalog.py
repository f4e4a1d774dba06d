"""The plugin catalogue ``registry.toml``: every known plugin, built-in or external, installed or not.

The file lives at the top of the source tree; ``PVSLAM_REGISTRY`` may point at another copy.  It is only read to
show ``pvslam plugins`` and to suggest an install command when a config names a plugin that is not installed.
"""
from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

_DEFAULT = Path(__file__).resolve().parent.parent / "registry.toml"


@dataclass
class Weights:
    name: str
    url: str
    sha256: str = ""  # full digest, or a prefix as in torch.hub file names
    license: str = ""
    size_mb: Optional[float] = None


@dataclass
class CatalogEntry:
    name: str
    interface: str
    entry_point: str
    description: str
    install: str = "built in"
    builtin: bool = False
    needs_gpu: bool = False
    status: str = "available"
    weights: list[Weights] = field(default_factory=list)


def catalog_path() -> Path:
    return Path(os.environ.get("PVSLAM_REGISTRY", _DEFAULT))


def load_catalog(path: Optional[Path] = None) -> list[CatalogEntry]:
    p = path or catalog_path()
    if not p.is_file():
        return []
    with open(p, "rb") as fh:
        data = tomllib.load(fh)
    out = []
    for i, raw in enumerate(data.get("plugin", [])):
        try:
            weights = [Weights(**w) for w in raw.get("weights", [])]
            fields = {k: v for k, v in raw.items() if k != "weights"}
            out.append(CatalogEntry(**fields, weights=weights))
        except TypeError as exc:
            raise ValueError(f"{p}: [[plugin]] entry {i} ({raw.get('name', '?')}): {exc}") from exc
    return out
