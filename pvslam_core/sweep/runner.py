"""``pvslam sweep``: plan the grid, skip finished cells, run the rest on an executor, write the results.

Sweep directory layout (``<output_dir>/<name>/``, stable, so running the same command again resumes)::

    sweep.toml        the sweep file as given          plan.json     every cell: name, sequence, seed, variant, key
    cells/<cell>/     one ordinary run directory per cell (plus the markers of .cells)
    status.json       each cell's state and error after the last invocation
    results/          cells.csv, summary.csv, results.md and the plots (see .results and .plots)
    stale/            finished cells whose config changed since (kept, not reused)

Ctrl-C: the tasks in flight are cancelled and their cells marked unfinished; finished cells keep their markers;
status.json is rewritten; the next invocation runs exactly the cells that are not finished.
"""
from __future__ import annotations

import os
import shutil
import sys
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

from ..outputs.metrics import write_json_atomic
from . import cells as C
from .progress import GridProgress
from .spec import Cell, SweepPlan, load_sweep


@dataclass
class SweepOutcome:
    directory: Path
    executor: str  # serial | ray | none (nothing to run)
    ran: list[str] = field(default_factory=list)  # cells run by this invocation (done or failed)
    skipped: list[str] = field(default_factory=list)  # already finished before
    failed: dict[str, str] = field(default_factory=dict)  # cell -> error (this invocation or kept from before)
    seconds: float = 0.0
    workers: int = 0
    threads: int = 0
    tables: dict[str, Path] = field(default_factory=dict)


@dataclass
class _Job:
    kind: str  # "prepare" | "cell"
    name: str
    payload: dict[str, Any]
    after: Optional[str] = None  # name of the prepare job that must finish first


def run_sweep(config: str | Path, overrides=None, output_dir: Optional[str | Path] = None,
              address: Optional[str] = None, workers: Optional[int] = None, serial: bool = False,
              retry_failed: bool = False, report_only: bool = False, progress: bool = True, registry=None,
              on_result: Optional[Callable[[str, dict], None]] = None) -> SweepOutcome:
    """Run (or resume) a sweep file; returns what ran.  ``on_result(cell, result)`` is called after every cell
    (a hook for tests and callers; an exception raised there stops the sweep like Ctrl-C)."""
    t0 = time.perf_counter()
    plan = load_sweep(config, overrides=overrides, output_dir=output_dir, registry=registry)
    root = plan.directory
    cells_root = root / "cells"
    cells_root.mkdir(parents=True, exist_ok=True)
    _write_plan(plan, Path(config))

    todo: list[Cell] = []
    out = SweepOutcome(root, "none")
    for cell in plan.cells:
        d = _cell_dir(cells_root, cell)
        st = C.cell_status(d, cell.key)
        if st == C.DONE or (st == C.FAILED and not retry_failed):
            out.skipped.append(cell.name)
            continue
        if report_only:  # touch nothing
            continue
        if st == "stale":  # finished with another config: keep it aside, never mix it into the table
            dest = root / "stale" / f"{cell.name}-{time.strftime('%Y%m%d-%H%M%S')}"
            dest.parent.mkdir(exist_ok=True)
            shutil.move(str(d), dest)
        else:
            C.clean(d, cells_root)  # unfinished / retried: start from an empty folder
        todo.append(cell)

    if todo and not report_only:
        sec = plan.section
        from .executors import make_executor

        executor = make_executor(serial, address, workers if workers is not None else sec.workers, sec.threads)
        out.executor, out.workers, out.threads = executor.kind, executor.slots, executor.threads
        try:
            _drive(plan, todo, executor, cells_root, out, overrides, progress, on_result)
        finally:
            executor.close()
            _write_status(plan, cells_root)
    else:
        _write_status(plan, cells_root)

    for cell in plan.cells:  # failures kept from earlier invocations are part of the outcome too
        fj = _cell_dir(cells_root, cell) / "failed.json"
        if fj.is_file() and cell.name not in out.failed:
            out.failed[cell.name] = C.read_marker(fj).get("error", "")
    out.tables = _results(plan, cells_root)
    out.seconds = time.perf_counter() - t0
    return out


def _cell_dir(cells_root: Path, cell: Cell) -> Path:
    d = cells_root / cell.name
    # cell names are sanitised; this is the belt to those braces: a cell folder is always a direct child.
    if d.resolve().parent != cells_root.resolve():
        raise RuntimeError(f"cell folder {d} escapes {cells_root}")
    return d


def _env() -> dict[str, str]:
    """The driver's PVSLAM_* variables (cache, registry, plugin selection) for the workers."""
    return {k: v for k, v in os.environ.items() if k.startswith("PVSLAM_")}


def _payload(cell: Cell, cells_root: Path, threads: int, overrides) -> dict[str, Any]:
    from ..config import _normalise_overrides

    cfg = cell.config.to_dict()
    cfg["run"].update(name=cell.name, output_dir=str(cells_root.resolve()), progress=False, threads=threads)
    return C.json_safe({
        "name": cell.name, "dir": str((cells_root / cell.name).resolve()), "key": cell.key, "threads": threads,
        "config": cfg, "meta": cell.meta, "overrides": {**_normalise_overrides(overrides), **cell.deltas},
        "env": _env(),
    })


def _jobs(todo: list[Cell], cells_root: Path, executor, overrides) -> list[_Job]:
    """Cells, each after a 'prepare' job for its dataset when several parallel cells share that dataset."""
    import json

    key = lambda c: json.dumps(c.config.to_dict()["dataset"], sort_keys=True)  # noqa: E731
    uses = Counter(key(c) for c in todo)
    jobs: list[_Job] = []
    prepared: dict[str, str] = {}
    for c in todo:
        k = key(c)
        after = None
        if executor.slots > 1 and uses[k] > 1:
            if k not in prepared:
                prepared[k] = f"prepare:{c.sequence}:seed{c.seed}:{len(prepared)}"
                jobs.append(_Job("prepare", prepared[k], {"name": prepared[k], "threads": executor.threads,
                                                          "dataset": json.loads(k), "env": _env()}))
            after = prepared[k]
        jobs.append(_Job("cell", c.name, _payload(c, cells_root, executor.threads, overrides), after))
    return jobs


def _drive(plan: SweepPlan, todo: list[Cell], executor, cells_root: Path, out: SweepOutcome, overrides,
           progress: bool, on_result) -> None:
    jobs = _jobs(todo, cells_root, executor, overrides)
    bar = GridProgress(len(plan.cells), len(out.skipped), executor.slots, enabled=progress,
                       label=f"sweep {plan.name} ({executor.kind}, {executor.slots} x {executor.threads} threads)")
    pending = deque(jobs)
    finished_prep: set[str] = set()
    inflight: dict[Any, _Job] = {}
    try:
        while pending or inflight:
            # Fill the free slots with the first jobs whose dataset is ready (queue order otherwise).
            for job in list(pending):
                if len(inflight) >= executor.slots:
                    break
                if job.after is not None and job.after not in finished_prep:
                    continue
                pending.remove(job)
                inflight[executor.submit(job.kind, job.payload)] = job
                if job.kind == "cell":
                    bar.start(job.name)
                elif not bar.phase:
                    bar.set_phase("generating datasets")
            assert inflight, "no runnable job"  # a prepare job is always queued before the cells that wait for it
            for handle, res in executor.wait(list(inflight), timeout=1.0):
                job = inflight.pop(handle)
                if job.kind == "prepare":
                    finished_prep.add(job.name)
                    if not any(j.kind == "prepare" for j in list(pending) + list(inflight.values())):
                        bar.set_phase("")
                    continue
                cell_dir = Path(job.payload["dir"])
                if res.get("crashed"):
                    if (cell_dir / "unfinished.json").is_file():  # SIGINT/SIGTERM inside the worker: run it again
                        res = {**res, "status": C.UNFINISHED}
                    else:  # the worker died (OOM kill, segfault) before it could record anything
                        C.mark_failed(cell_dir, job.payload["key"], res["error"], res.get("traceback", ""),
                                      res.get("seconds"))
                out.ran.append(job.name)
                if res["status"] == C.FAILED:
                    out.failed[job.name] = res.get("error", "")
                bar.finish(job.name, res["status"], res.get("error", ""))
                if on_result is not None:
                    on_result(job.name, res)
            bar.draw()
    except BaseException:  # Ctrl-C (or a failing callback): leave every in-flight cell marked unfinished
        executor.cancel(list(inflight))
        for job in inflight.values():
            if job.kind == "cell":
                C.mark_unfinished(Path(job.payload["dir"]), "sweep interrupted")
        bar.close()
        raise
    bar.close()


def _write_plan(plan: SweepPlan, source: Path) -> None:
    root = plan.directory
    if source.is_file():
        shutil.copyfile(source, root / "sweep.toml")
    write_json_atomic(root / "plan.json", {
        "name": plan.name, "source": plan.source, "sequences": plan.sequences, "variants": plan.variants,
        "cells": [{"name": c.name, **c.meta} for c in plan.cells]})


def _write_status(plan: SweepPlan, cells_root: Path) -> None:
    rows = []
    for c in plan.cells:
        d = cells_root / c.name
        st = C.cell_status(d, c.key)
        row = {"name": c.name, **c.meta, "status": st}
        if st == C.FAILED:
            row["error"] = C.read_marker(d / "failed.json").get("error", "")
        rows.append(row)
    counts = Counter(r["status"] for r in rows)
    write_json_atomic(plan.directory / "status.json", {"counts": dict(counts), "cells": rows,
                                                       "time": time.strftime("%Y-%m-%dT%H:%M:%S")})


def _results(plan: SweepPlan, cells_root: Path) -> dict[str, Path]:
    try:
        from .results import write_results
    except ImportError as exc:  # pandas missing: the cells are fine, only the table needs the extra
        print(f"pvslam sweep: no results table ({exc}); pip install 'pvslam[sweep]'", file=sys.stderr)
        return {}
    return write_results(plan, cells_root, plan.directory / "results")
