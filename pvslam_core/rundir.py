"""Run directories: creation, the resolved config, overrides, versions and the log file.

Every run directory holds ``config.json`` (the resolved config, reloadable through the models), ``overrides.json``,
``versions.json`` (pvslam, python, libraries, the plugins used, the git revision) and ``log.txt``.  The working
directory of the process is never changed; paths are resolved against it once.
"""
from __future__ import annotations

import contextlib
import json
import logging
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Optional

from .config import COMPONENTS, ResolvedConfig

LOG = logging.getLogger("pvslam")


def check_name(name: str, what: str = "run.name") -> str:
    """``name`` as one plain folder name inside the output directory, or ValueError saying why not.

    A run or variant name becomes a directory name under ``run.output_dir``: a separator, ``..`` or an absolute
    path would let it write (and overwrite) anywhere, so such names are rejected rather than silently rewritten.
    """
    if not isinstance(name, str) or not name.strip():
        raise ValueError(f"{what} must be a non-empty folder name, got {name!r}")
    problems = [f"contains {c!r}" for c in ("/", "\\", "\x00") if c in name]
    if any(ord(c) < 32 for c in name.replace("\x00", "")):
        problems.append("contains control characters")
    if name in (".", ".."):
        problems.append("is a dot name")
    if Path(name).is_absolute():
        problems.append("is absolute")
    if len(name) > 200:
        problems.append("is longer than 200 characters")
    if problems:
        raise ValueError(f"{what} {name!r} {', '.join(problems)}: a name must stay inside the output directory, "
                         "so it is one folder name (no path separators, no '..', not absolute)")
    return name


def inside_dir(base: Path, path: Path) -> bool:
    """Whether ``path`` resolves (symlinks followed) to ``base`` or below it."""
    try:
        return Path(path).resolve().is_relative_to(Path(base).resolve())
    except (OSError, RuntimeError):
        return False


def ensure_output_dir(output_dir: str | Path, what: str = "run.output_dir") -> Path:
    """Create ``output_dir`` (and parents); a path that exists as a file, or below a file, is a clear error."""
    base = Path(output_dir)
    for p in (base, *base.parents):
        if p.exists() and not p.is_dir():
            raise NotADirectoryError(f"{what} {str(base)!r}: {str(p)!r} exists and is not a directory")
    try:
        base.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise type(exc)(exc.errno, f"{what}: cannot create the folder ({exc.strerror})", str(base)) from exc
    return base


def make_run_dir(output_dir: str | Path, name: str) -> Path:
    """``<output_dir>/<name>-YYYYmmdd-HHMMSS`` (with a numeric suffix if it exists already)."""
    check_name(name)
    base = ensure_output_dir(output_dir)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    for n in range(1000):
        cand = base / (f"{name}-{stamp}" if n == 0 else f"{name}-{stamp}-{n}")
        try:
            cand.mkdir()
        except FileExistsError:
            continue
        if not inside_dir(base, cand):  # defence in depth: check_name should make this impossible
            cand.rmdir()
            raise ValueError(f"run directory {cand} would lie outside {base}")
        return cand
    raise RuntimeError(f"cannot create a run directory under {base}")


ABLATION_FILES = ("comparison.json",)  # what an ablation writes beside its variants' folders


def check_variant_name(name: str) -> str:
    """:func:`check_name` for an ablation variant, which also must not be the name of a file the ablation writes."""
    check_name(name, what="variant name")
    if name in ABLATION_FILES:
        raise ValueError(f"variant name {name!r} is the ablation's own {name}; rename the variant")
    return name


def make_variant_dir(base: Path, name: str) -> Path:
    """``<base>/<name>`` for an ablation variant; the name must stay inside ``base``."""
    check_variant_name(name)
    d = base / name
    if not inside_dir(base, d):
        raise ValueError(f"variant name {name!r}: {d} resolves outside {base}")
    return d


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
    from .outputs._atomic import atomic_write_text

    atomic_write_text(path, json.dumps(obj, indent=2, default=str) + "\n")


def init_run_dir(run_dir: Path, resolved: ResolvedConfig, registry, overrides: dict[str, Any]) -> None:
    from .outputs._atomic import atomic_write_text

    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(run_dir / "config.json", resolved.to_json())
    write_json(run_dir / "overrides.json", {"source": resolved.source, "overrides": overrides})
    write_json(run_dir / "versions.json", versions(resolved, registry))


def remove_unused_run_dir(run_dir: Path) -> bool:
    """Remove a run directory this process created when the run stopped before it wrote a result (no frame: only
    the config, versions and log files, an empty panoptic journal or a partial metrics.json); True if removed."""
    if (run_dir / "trajectory.txt").exists() or any((run_dir / "panoptic").glob("*.png")):
        return False
    import shutil

    shutil.rmtree(run_dir, ignore_errors=True)
    return not run_dir.exists()


class _LogFile(logging.FileHandler):
    """``log.txt``; a write that fails (a full disk) is said once on the console and the file is given up, so a
    log line can never replace the error that stopped the run (e.g. the files :class:`OutputWriteError` names)."""

    failed: Optional[str] = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.failed is None:
            super().emit(record)

    def flush(self) -> None:
        try:
            super().flush()
        except OSError as exc:
            self._give_up(exc)

    def close(self) -> None:
        try:
            super().close()
        except OSError as exc:
            self._give_up(exc)

    def handleError(self, record: logging.LogRecord) -> None:
        exc = sys.exc_info()[1]
        if isinstance(exc, OSError):
            self._give_up(exc)
        else:
            super().handleError(record)

    def _give_up(self, exc: OSError) -> None:
        if self.failed is None:
            self.failed = exc.strerror or str(exc)
            print(f"pvslam: warning: cannot write {self.baseFilename} ({self.failed}); the rest of the log goes "
                  "unsaved", file=sys.stderr)
        stream, self.stream = self.stream, None
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()


class RunLog:
    """Attach a file handler for ``log.txt`` to the ``pvslam`` logger for the duration of a run."""

    def __init__(self, run_dir: Optional[Path], level: str = "INFO"):
        self.handler: Optional[logging.Handler] = None
        self.level = getattr(logging, level)
        if run_dir is not None:
            self.handler = _LogFile(run_dir / "log.txt")
            self.handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
            self.handler.setLevel(self.level)

    # the core logs to "pvslam.*", plugins (readers, frontends) to "pvslam_plugins.*": log.txt gets both
    LOGGERS = ("pvslam", "pvslam_plugins")

    def __enter__(self) -> "RunLog":
        for name in self.LOGGERS:
            log = logging.getLogger(name)
            if self.handler is not None:
                log.addHandler(self.handler)
            if log.level == logging.NOTSET or log.level > self.level:
                log.setLevel(self.level)
        return self

    def __exit__(self, *exc) -> None:
        if self.handler is not None:
            for name in self.LOGGERS:
                logging.getLogger(name).removeHandler(self.handler)
            self.handler.close()
