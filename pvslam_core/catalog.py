"""The plugin catalogue ``registry.toml``: every known plugin, built-in or external, installed or not.

The file lives at the top of the source tree; ``PVSLAM_REGISTRY`` may point at another copy.  It is only read to
show ``pvslam plugins`` and to suggest an install command when a config names a plugin that is not installed.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the `tomli` package (a dependency there) is the same parser
    import tomli as tomllib

_DEFAULT = Path(__file__).resolve().parent.parent / "registry.toml"


@dataclass
class Weights:
    """One downloadable checkpoint (``[[plugin.weights]]``); ``pvslam weights`` fetches it (see weights.py)."""

    name: str
    url: str
    sha256: str = ""  # full digest, or a prefix as in torch.hub file names ("" = not known)
    license: str = ""
    size_mb: Optional[float] = None
    md5: str = ""  # full digest or prefix (detectron2 model-zoo file names carry an MD5 prefix)
    filename: str = ""  # name in the cache; default: the URL's last path component
    aliases: list[str] = field(default_factory=list)  # other names accepted by `pvslam weights` / `weights = ...`
    used_by: str = ""  # which plugin / variant loads it
    manual: bool = False  # no direct download (login or share page): fetch explains what to do instead
    note: str = ""  # provenance, and why a checksum is missing when it is
    plugin: str = ""  # filled in by load_catalog: the [[plugin]] entry that lists these weights


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
            weights = [Weights(**{**w, "plugin": raw.get("name", "")}) for w in raw.get("weights", [])]
            fields = {k: v for k, v in raw.items() if k != "weights"}
            out.append(CatalogEntry(**fields, weights=weights))
        except TypeError as exc:
            raise ValueError(f"{p}: [[plugin]] entry {i} ({raw.get('name', '?')}): {exc}") from exc
    return out
