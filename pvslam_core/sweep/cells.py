"""One cell of a sweep on disk, and the functions that workers execute (serially in-process or as Ray tasks).

A cell folder ``<sweep>/cells/<name>/`` is an ordinary run directory (config.json, metrics.json, trajectory.txt,
...) plus the sweep's markers:

* ``cell.json``       written when the cell starts: sequence, seed, variant, config key, host, pid;
* ``done.json``       written LAST, atomically, after the run wrote its metrics: the cell is finished;
* ``failed.json``     the run raised: the error in one line (``error.txt`` holds the traceback);
* ``unfinished.json`` the sweep was interrupted while this cell ran (Ctrl-C).

State is read from these files only, so it is consistent whatever stopped the sweep: a folder without
``done.json`` or ``failed.json`` (interrupted, or killed outright) is run again, into a cleaned folder.
The worker functions take and return plain dicts (picklable, no pydantic objects cross process boundaries).
"""
from __future__ import annotations

import json
import os
import shutil
import socket
import time
import traceback
from pathlib import Path
from typing import Any, Optional

from ..outputs.metrics import read_json, write_json_atomic

DONE, FAILED, UNFINISHED, PENDING = "done", "failed", "unfinished", "pending"
MARKERS = ("done.json", "failed.json", "unfinished.json")


# ---------------------------------------------------------------------------------------------- markers --
def cell_status(cell_dir: Path, key: Optional[str] = None) -> str:
    """done | failed | unfinished | pending (no folder) | stale (done or failed with another config key)."""
    cell_dir = Path(cell_dir)
    for marker, status in (("done.json", DONE), ("failed.json", FAILED)):
        if (cell_dir / marker).is_file():
            if key is not None and read_marker(cell_dir / marker).get("key") not in (None, key):
                return "stale"
            return status
    return UNFINISHED if cell_dir.exists() else PENDING


def read_marker(path: Path) -> dict:
    try:
        data = read_json(path)
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def mark_unfinished(cell_dir: Path, reason: str) -> None:
    """Record an interruption (never over a finished cell's marker)."""
    cell_dir = Path(cell_dir)
    if cell_dir.is_dir() and not any((cell_dir / m).is_file() for m in ("done.json", "failed.json")):
        write_json_atomic(cell_dir / "unfinished.json", {"status": UNFINISHED, "reason": reason, "time": _now()})


def mark_failed(cell_dir: Path, key: str, error: str, tb: str, seconds: Optional[float] = None) -> None:
    cell_dir = Path(cell_dir)
    cell_dir.mkdir(parents=True, exist_ok=True)
    (cell_dir / "error.txt").write_text(tb)
    (cell_dir / "unfinished.json").unlink(missing_ok=True)
    write_json_atomic(cell_dir / "failed.json", {"status": FAILED, "key": key, "error": error, "seconds": seconds,
                                                 "time": _now()})


def clean(cell_dir: Path, root: Path) -> None:
    """Remove a cell folder before (re)running it; refuses anything outside ``root``."""
    cell_dir, root = Path(cell_dir).resolve(), Path(root).resolve()
    if root not in cell_dir.parents:
        raise RuntimeError(f"refusing to remove {cell_dir}: not inside the sweep folder {root}")
    if cell_dir.exists():
        shutil.rmtree(cell_dir)


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S")


# ------------------------------------------------------------------------------------------ worker side --
def _setup(payload: dict[str, Any]) -> None:
    """Per-task process setup: the driver's PVSLAM_* variables and folder (a Ray worker starts elsewhere), and
    the thread budget of one run."""
    os.environ.update(payload.get("env", {}))
    cwd = payload.get("cwd")
    if cwd and os.path.isdir(cwd) and os.getcwd() != cwd:
        os.chdir(cwd)
    threads = int(payload["threads"])
    import cv2
    import torch

    torch.set_num_threads(max(1, threads))
    cv2.setNumThreads(max(1, threads))


def execute_cell(payload: dict[str, Any]) -> dict[str, Any]:
    """Run one cell into ``payload["dir"]``; never raises for a failing run (the failure is recorded)."""
    from ..config import load_config
    from ..pipeline import run

    cell_dir = Path(payload["dir"])
    name, key = payload["name"], payload["key"]
    t0 = time.perf_counter()
    try:
        _setup(payload)
        cell_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(cell_dir / "cell.json", {**payload["meta"], "name": name, "threads": payload["threads"],
                                                   "host": socket.gethostname(), "pid": os.getpid(),
                                                   "started": _now()})
        resolved = load_config(payload["config"])
        # The same entry point as `pvslam run`: config.json, overrides.json, versions.json, log.txt, metrics.json...
        result = run(resolved, run_dir=cell_dir, overrides=payload.get("overrides", {}))
    except KeyboardInterrupt:
        mark_unfinished(cell_dir, "interrupted (Ctrl-C)")
        raise
    except BaseException as exc:  # the sweep goes on: record and report
        seconds = time.perf_counter() - t0
        error = f"{type(exc).__name__}: {exc}".strip()
        mark_failed(cell_dir, key, error.splitlines()[0][:500] if error else type(exc).__name__,
                    traceback.format_exc(), seconds)
        return {"name": name, "status": FAILED, "error": error.splitlines()[0] if error else "", "seconds": seconds}
    seconds = time.perf_counter() - t0
    (cell_dir / "unfinished.json").unlink(missing_ok=True)
    write_json_atomic(cell_dir / "done.json", {"status": DONE, "key": key, "seconds": seconds, "time": _now(),
                                               "fps": result.metrics.get("timing", {}).get("fps")})
    return {"name": name, "status": DONE, "error": "", "seconds": seconds}


def prepare_dataset(payload: dict[str, Any]) -> dict[str, Any]:
    """Build a dataset reader and read its description once, so that a generated sequence (built-in scenarios)
    is written to the cache by one task instead of by every variant's cell at the same time."""
    import torch

    from ..config import load_config
    from ..interfaces import BuildContext
    from ..registry import get_registry

    t0 = time.perf_counter()
    try:
        _setup(payload)
        resolved = load_config({"dataset": payload["dataset"]})
        spec = get_registry().get("dataset", resolved.pipeline.dataset.plugin)
        reader = spec.factory(resolved.models["dataset"], BuildContext(device=torch.device("cpu")))
        reader.info()
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # the cells that use it will fail and record the error themselves
        return {"name": payload["name"], "status": FAILED, "error": f"{type(exc).__name__}: {exc}",
                "seconds": time.perf_counter() - t0}
    return {"name": payload["name"], "status": DONE, "error": "", "seconds": time.perf_counter() - t0}


def json_safe(obj: Any) -> Any:
    """Round-trip through JSON: the payloads hold only plain types."""
    return json.loads(json.dumps(obj, default=str))
