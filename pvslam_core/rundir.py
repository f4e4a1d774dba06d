"""Run directories: creation, the resolved config, overrides, versions and the log file.

Every run directory holds ``config.json`` (the resolved config, reloadable through the models), ``overrides.json``,
``versions.json`` (pvslam, python, libraries, the plugins used, the git revision) and ``log.txt``.  The working
directory of the process is never changed; paths are resolved against it once.
"""
from __future__ import annotations

import json
import logging
import platform
import subprocess
import time
from pathlib import Path
from typing import Any, Optional

from .config import COMPONENTS, ResolvedConfig

LOG = logging.getLogger("pvslam")


def make_run_dir(output_dir: str | Path, name: str) -> Path:
    """``<output_dir>/<name>-YYYYmmdd-HHMMSS`` (with a numeric suffix if it exists already)."""
    base = Path(output_dir)
    base.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    for n in range(1000):
        cand = base / (f"{name}-{stamp}" if n == 0 else f"{name}-{stamp}-{n}")
        try:
            cand.mkdir()
            return cand
        except FileExistsError:
            continue
    raise RuntimeError(f"cannot create a run directory under {base}")


def git_revision() -> dict[str, Any]:
    """Git revision of the pvslam source tree (when it is a checkout), without changing directory."""
    src = Path(__file__).resolve().parent
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=src, capture_output=True, text=True, timeout=5)
        if rev.returncode != 0:
            return {"revision": None}
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=src,
                               capture_output=True, text=True, timeout=5)
        return {"revision": rev.stdout.strip(), "dirty": bool(dirty.stdout.strip())}
    except (OSError, subprocess.SubprocessError):
        return {"revision": None}


def versions(resolved: ResolvedConfig, registry) -> dict[str, Any]:
    from importlib import metadata

    def ver(dist: str) -> Optional[str]:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    plugins = {}
    for name in COMPONENTS:
        comp = getattr(resolved.pipeline, name)
        if not comp.enabled:
            plugins[name] = None
            continue
        spec = registry.get(name, comp.plugin)
        plugins[name] = {"plugin": spec.name, "entry_point": spec.entry_point,
                         "distribution": spec.distribution, "version": spec.version}
    return {
        "pvslam": ver("pvslam"),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "libraries": {d: ver(d) for d in ("torch", "numpy", "opencv-python-headless", "pydantic", "pluggy", "evo")},
        "plugins": plugins,
        "git": git_revision(),
    }


def write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=str))
    tmp.replace(path)


def init_run_dir(run_dir: Path, resolved: ResolvedConfig, registry, overrides: dict[str, Any]) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(resolved.to_json())
    write_json(run_dir / "overrides.json", {"source": resolved.source, "overrides": overrides})
    write_json(run_dir / "versions.json", versions(resolved, registry))


class RunLog:
    """Attach a file handler for ``log.txt`` to the ``pvslam`` logger for the duration of a run."""

    def __init__(self, run_dir: Optional[Path], level: str = "INFO"):
        self.handler: Optional[logging.Handler] = None
        self.level = getattr(logging, level)
        if run_dir is not None:
            self.handler = logging.FileHandler(run_dir / "log.txt")
            self.handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
            self.handler.setLevel(self.level)

    def __enter__(self) -> "RunLog":
        if self.handler is not None:
            LOG.addHandler(self.handler)
        if LOG.level == logging.NOTSET or LOG.level > self.level:
            LOG.setLevel(self.level)
        return self

    def __exit__(self, *exc) -> None:
        if self.handler is not None:
            LOG.removeHandler(self.handler)
            self.handler.close()
