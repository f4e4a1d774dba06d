"""Where a benchmark result comes from, and the refusal to write one that cannot say.

Every bench tool that writes a result file calls :func:`check` before it starts measuring and :func:`write_json`
(or :func:`write_text`) at the end.  The result then carries ``provenance``: the commit of the measured code
(``git rev-parse HEAD`` of the checkout that ``pvslam_core`` is imported from), whether that checkout had
uncommitted changes to tracked files (``dirty``, the convention of a run directory's ``versions.json``) and the hash
of those changes, the command line, the machine and the library versions.  Without a commit there is no result:
outside a git checkout, or when the bench tools and the imported ``pvslam_core`` come from different checkouts, the
tool stops with :class:`ProvenanceError` before it measures anything.  Result files do not belong in ``bench/``
(the tools and peers live there); the default place is ``runs/bench/`` (ignored by git).

To measure one commit while editing another, check it out elsewhere (``git worktree add /tmp/m COMMIT``) and run
the tools there with that checkout installed or first on ``PYTHONPATH`` (``/tmp/m:/tmp/m/plugins``).
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import importlib.util
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path
from typing import Any, Optional

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "bench"
RESULTS_DIR = ROOT / "runs" / "bench"  # the default place of result files (ignored by git)
_SHA = re.compile(r"[0-9a-f]{40}")


class ProvenanceError(RuntimeError):
    """A result whose commit cannot be recorded (or a result file that records none)."""


def _git(args: list[str], cwd: Path) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=60,
                          check=True).stdout


def checkout_state(path: Path) -> dict[str, Any]:
    """``{"commit", "dirty", "diff_sha256", "checkout"}`` of the git checkout that holds ``path``."""
    path = Path(path)
    where = path if path.is_dir() else path.parent
    try:
        top = _git(["rev-parse", "--show-toplevel"], where).strip()
        commit = _git(["rev-parse", "HEAD"], where).strip()
        status = _git(["status", "--porcelain", "--untracked-files=no"], Path(top))
        diff = _git(["diff", "HEAD", "--binary"], Path(top)) if status.strip() else ""
    except (OSError, subprocess.SubprocessError) as exc:
        err = getattr(exc, "stderr", "") or exc
        raise ProvenanceError(f"{path} is not in a git checkout, so the commit of the measured code cannot be "
                              f"recorded and no result is written (git: {str(err).strip()[:200]}); run the bench "
                              f"tools from a git checkout (git worktree add DIR COMMIT)") from None
    if not _SHA.fullmatch(commit):
        raise ProvenanceError(f"{top}: `git rev-parse HEAD` gave {commit!r}, not a commit")
    return {"commit": commit, "dirty": bool(status.strip()),
            "diff_sha256": hashlib.sha256(diff.encode()).hexdigest() if status.strip() else None,
            "checkout": str(Path(top).resolve())}


def library_dir() -> Path:
    """The folder ``pvslam_core`` is imported from (without importing it)."""
    spec = importlib.util.find_spec("pvslam_core")
    if spec is None or not spec.origin:
        raise ProvenanceError("pvslam_core is not importable: install the checkout (pip install -e .)")
    return Path(spec.origin).resolve().parent


def _versions() -> dict[str, Optional[str]]:
    from importlib import metadata

    out = {}
    for dist in ("torch", "numpy", "opencv-python-headless", "opencv-python"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    return out


def provenance(argv: Optional[list[str]] = None) -> dict[str, Any]:
    """The provenance of a measurement starting now (raises :class:`ProvenanceError` without a commit)."""
    lib = checkout_state(library_dir())
    tools = checkout_state(BENCH)
    if lib["checkout"] != tools["checkout"]:
        raise ProvenanceError(f"the bench tools of {tools['checkout']} would measure pvslam_core imported from "
                              f"{lib['checkout']}: a result would name the wrong commit; install this checkout "
                              f"(pip install -e .) or put it first on PYTHONPATH")
    return {"commit": lib["commit"], "dirty": lib["dirty"], "diff_sha256": lib["diff_sha256"],
            "argv": list(sys.argv if argv is None else argv), "host": platform.node(), "cpus": os.cpu_count(),
            "python": platform.python_version(), "libraries": _versions(),
            "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}


def check_path(path: str | Path) -> Path:
    """A result path outside the ``bench/`` source folder (raises :class:`ProvenanceError` otherwise)."""
    p = Path(path).resolve()
    if p == BENCH or BENCH in p.parents:
        raise ProvenanceError(f"{path}: result files do not go into bench/ (tools and peers only); write them under "
                              f"{RESULTS_DIR.relative_to(ROOT)}/ or anywhere outside the source tree")
    return p


def check(path: str | Path, argv: Optional[list[str]] = None) -> dict[str, Any]:
    """Before measuring: the provenance, and a usable result path; raises :class:`ProvenanceError`."""
    check_path(path)
    prov = provenance(argv)
    if prov["dirty"]:
        print(f"provenance: the checkout has uncommitted changes to tracked files; the result records commit "
              f"{prov['commit'][:12]} with dirty = true", file=sys.stderr)
    return prov


def _finish(prov: Optional[dict[str, Any]]) -> dict[str, Any]:
    """The provenance at write time: the one taken at the start, marked if the checkout changed since."""
    if prov is None:
        return {**provenance(), "finished": _now()}
    now = checkout_state(library_dir())
    changed = (now["commit"], now["diff_sha256"]) != (prov["commit"], prov["diff_sha256"])
    if changed:
        print(f"provenance: the checkout changed while measuring (now {now['commit'][:12]}, dirty = {now['dirty']}); "
              f"the result is marked changed_during_run", file=sys.stderr)
    return {**prov, "finished": _now(), **({"changed_during_run": True} if changed else {})}


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def write_json(path: str | Path, payload: dict[str, Any], prov: Optional[dict[str, Any]] = None) -> Path:
    """Write ``{"provenance": ..., **payload}`` atomically to ``path`` (refused without a commit)."""
    p = check_path(path)
    data = {"provenance": _finish(prov), **{k: v for k, v in payload.items() if k != "provenance"}}
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str), encoding="utf-8")
    os.replace(tmp, p)
    return p


def write_text(path: str | Path, text: str, prov: Optional[dict[str, Any]] = None) -> Path:
    """A text result (e.g. Markdown tables) whose first line is an HTML comment holding the provenance."""
    p = check_path(path)
    head = f"<!-- provenance: {json.dumps(_finish(prov), default=str)} -->\n"
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(head + text, encoding="utf-8")
    os.replace(tmp, p)
    return p


def read_json(path: str | Path) -> dict[str, Any]:
    """A result file with its provenance; refuses one that records no commit.  Files written before the provenance
    block existed (a top-level ``commit`` of 40 hex digits) read with ``dirty = None`` (not recorded)."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    prov = data.get("provenance") if isinstance(data, dict) else None
    if not prov and isinstance(data, dict) and _SHA.fullmatch(str(data.get("commit", ""))):
        prov = {"commit": data["commit"], "dirty": None}
    if not prov or not _SHA.fullmatch(str(prov.get("commit", ""))):
        raise ProvenanceError(f"{path}: no commit recorded, so it is not a result of any code")
    data["provenance"] = prov
    return data


def run_dir_provenance(run_dir: str | Path) -> dict[str, Any]:
    """The provenance a pvslam run directory records (``versions.json``: git revision and dirty flag)."""
    versions = json.loads((Path(run_dir) / "versions.json").read_text(encoding="utf-8"))
    git = versions.get("git") or {}
    if not _SHA.fullmatch(str(git.get("revision") or "")):
        raise ProvenanceError(f"{run_dir}: versions.json records no git revision")
    return {"commit": git["revision"], "dirty": git.get("dirty")}


def fail(exc: ProvenanceError) -> int:
    """The tools' exit on a provenance error: one clear line on stderr, exit status 2."""
    print(f"error: {exc}", file=sys.stderr)
    return 2
