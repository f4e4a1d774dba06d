"""Ablation sweeps: datasets/sequences x seeds x variants, one ordinary run directory per cell, on Ray or serially.

    pvslam sweep --config configs/sweep_table7.toml [--address ADDR] [--workers N] [--serial]

* :mod:`.spec`      the sweep file (pydantic, extra="forbid") and its expansion into cells with stable names
* :mod:`.cells`     a cell on disk (done / failed / unfinished markers) and the functions workers run
* :mod:`.executors` Ray (local instance sized to the machine, or ``--address``) and the in-process fallback
* :mod:`.runner`    resume, drive the executor, Ctrl-C handling, status.json
* :mod:`.progress`  the grid's progress line on stderr
* :mod:`.results`, :mod:`.plots`  the pandas table (CSV + Markdown, mean ± std over seeds, best variant) and plots

Nothing heavy is imported here: ``pvslam --help`` stays fast.
"""
from __future__ import annotations

__all__ = ["run_sweep", "load_sweep"]


def __getattr__(name: str):
    if name == "run_sweep":
        from .runner import run_sweep

        return run_sweep
    if name == "load_sweep":
        from .spec import load_sweep

        return load_sweep
    raise AttributeError(name)
