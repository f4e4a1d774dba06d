"""The Python API: run a pipeline or an ablation from code, re-evaluate a run directory.

    from pvslam_core import load_config, run_config
    result = run_config("configs/default.toml", overrides=["loop.plugin=none"])
    print(result.metrics["ate"]["rmse"], result.run_dir)
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional, Union

from .config import PipelineConfig, ResolvedConfig, load_ablation, load_config, _normalise_overrides
from .types import RunResult

ConfigLike = Union[None, str, Path, dict, PipelineConfig, ResolvedConfig]


def run_config(config: ConfigLike = None, overrides=None, run_dir: Optional[Union[str, Path]] = None,
               registry=None) -> RunResult:
    """Run one pipeline. ``config`` is a TOML/JSON path, a dict shaped like the TOML (``{"dataset": {"plugin":
    "kitti", ...}, ...}``), a :class:`PipelineConfig`, a :class:`ResolvedConfig`, or None (built-in default)."""
    from .pipeline import run

    if isinstance(config, ResolvedConfig):
        if overrides:
            raise ValueError("overrides apply to config files; pass a path or apply them before resolving")
        resolved = config
    else:
        resolved = load_config(config, overrides=overrides, registry=registry)
    return run(resolved, run_dir=run_dir, registry=registry, overrides=_normalise_overrides(overrides))


def run_ablation(path: Union[str, Path], overrides=None, registry=None) -> list[tuple[str, RunResult]]:
    """Run every ``[[variant]]`` of an ablation file, each into ``<ablation run dir>/<variant name>/``."""
    from .pipeline import run
    from .report import comparison_rows
    from .rundir import make_run_dir, write_json

    variants = load_ablation(path, overrides=overrides, registry=registry)
    first = variants[0].config.pipeline.run
    base = make_run_dir(first.output_dir, Path(path).stem)
    results: list[tuple[str, RunResult]] = []
    for v in variants:
        res = run(v.config, run_dir=base / v.name, registry=registry,
                  overrides={**_normalise_overrides(overrides), **v.deltas})
        results.append((v.name, res))
        write_json(base / "comparison.json", comparison_rows(results))
    return results


def evaluate_run_dir(run_dir: Union[str, Path], registry=None) -> dict[str, Any]:
    """Recompute the metrics of a run directory (ground truth re-read through the run's dataset config)."""
    from .run_outputs import evaluate_saved_run

    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file():
        raise FileNotFoundError(f"{run_dir}: not a pvslam run directory (no config.json)")
    resolved = load_config(run_dir / "config.json", registry=registry)
    timing = {}
    if (run_dir / "metrics.json").is_file():
        timing = json.loads((run_dir / "metrics.json").read_text()).get("timing", {})
    return evaluate_saved_run(run_dir, resolved, timing, registry=registry)
