"""The Python API: run a pipeline or an ablation from code, run on a path, track live frames, re-evaluate a run.

    from pvslam_core import load_config, run_config
    result = run_config("configs/default.toml", overrides=["loop.plugin=none"])
    print(result.metrics["ate"]["rmse"], result.run_dir)

    from pvslam_core.api import run_path, Tracker
    result = run_path("clip.mp4", calib="calib.txt")          # what `pvslam run clip.mp4 --calib calib.txt` does
    with Tracker(intrinsics="calib.txt") as tracker:           # frames one at a time (see pvslam_core.tracker)
        pose, frame_result = tracker.track(image, timestamp)
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional, Union

from .config import PipelineConfig, ResolvedConfig, load_ablation, load_config, _normalise_overrides
from .tracker import TrackedFrame, Tracker  # noqa: F401 - re-exported: the streaming API
from .types import RunResult

LOG = logging.getLogger("pvslam")

ConfigLike = Union[None, str, Path, dict, PipelineConfig, ResolvedConfig]


def run_config(config: ConfigLike = None, overrides=None, run_dir: Optional[Union[str, Path]] = None,
               registry=None, observer=None) -> RunResult:
    """Run one pipeline. ``config`` is a TOML/JSON path, a dict shaped like the TOML (``{"dataset": {"plugin":
    "kitti", ...}, ...}``), a :class:`PipelineConfig`, a :class:`ResolvedConfig`, or None (built-in default).
    ``observer``: a :class:`~pvslam_core.observer.RunObserver` (e.g. the rerun viewer) that watches the run."""
    from .pipeline import run

    if isinstance(config, ResolvedConfig):
        if overrides:
            raise ValueError("overrides apply to config files; pass a path or apply them before resolving")
        resolved = config
    else:
        resolved = load_config(config, overrides=overrides, registry=registry)
    return run(resolved, run_dir=run_dir, registry=registry, overrides=_normalise_overrides(overrides),
               observer=observer)


def path_overrides(path: Union[str, Path], calib: Optional[Union[str, Path]] = None, overrides=None,
                   registry=None, config: ConfigLike = None) -> tuple[dict[str, Any], Any]:
    """The overrides that point a pipeline at ``path`` (the reader detected from it, ``calib`` as its calibration,
    a run name from the file name unless ``overrides`` set one), and the detection.  The ``[dataset]`` keys of
    ``config`` that the detected reader has still apply (``resize``, ``stride``, ``end`` ...); the others are
    dropped with a notice that names them (see :func:`~pvslam_core.datasets.detect.merge_config_section`)."""
    from .adapt import NOTICE
    from .datasets.detect import dataset_section, merge_config_section, run_name_for

    det = dataset_section(path, calib, registry)
    ov = _normalise_overrides(overrides)
    table = _config_dataset_table(config)
    section, taken, dropped = merge_config_section(det, table, registry)
    where = config if isinstance(config, (str, Path)) else "the config"
    if taken:
        NOTICE.warning("dataset: from %s: %s", where, ", ".join(f"{k}={section[k]!r}" for k in taken))
    for why, keys in dropped.items():
        NOTICE.warning("dataset: %s in %s ignored: %s", ", ".join(keys), where, why)
    out: dict[str, Any] = {"dataset": section}
    if "run.name" not in ov:
        out["run.name"] = run_name_for(path)
    return {**out, **{k: v for k, v in ov.items() if not k.startswith("dataset.") and k != "dataset"},
            **{k: v for k, v in ov.items() if k.startswith("dataset.")}}, det


def _config_dataset_table(config: ConfigLike) -> dict[str, Any]:
    """The ``[dataset]`` table of a config as written (no defaults filled in): {} without a config."""
    from .config import read_config_text, read_toml

    if config is None or isinstance(config, ResolvedConfig):
        return {}
    if isinstance(config, PipelineConfig):
        table: Any = config.dataset.model_dump(mode="json")
    elif isinstance(config, dict):
        table = config.get("dataset")
    elif str(config).endswith(".json"):
        try:
            table = json.loads(read_config_text(config)).get("dataset")
        except (json.JSONDecodeError, AttributeError):
            return {}  # load_config reports it
    else:
        table = read_toml(config).get("dataset")
    if isinstance(table, str):  # `dataset = "kitti"`
        return {"plugin": table}
    return dict(table) if isinstance(table, dict) else {}


def run_path(path: Union[str, Path], calib: Optional[Union[str, Path]] = None, config: ConfigLike = None,
             overrides=None, run_dir: Optional[Union[str, Path]] = None, registry=None, observer=None) -> RunResult:
    """Run on a video file, an image folder or a dataset layout detected from ``path`` (see
    :mod:`pvslam_core.datasets.detect`); ``config`` supplies everything else, its ``[dataset]`` keys that the
    detected reader has included (None: the default).  Components that need labels the data lacks are switched off
    (see :mod:`pvslam_core.adapt`)."""
    from .adapt import NOTICE

    if isinstance(config, ResolvedConfig):
        raise ValueError("run_path takes a config path, dict or PipelineConfig (the dataset is replaced)")
    ov, det = path_overrides(path, calib, overrides, registry, config=config)
    NOTICE.warning("input: %s (%s reader)", det.description, det.plugin)
    return run_config(config, overrides=ov, run_dir=run_dir, registry=registry, observer=observer)


def run_ablation(path: Union[str, Path], overrides=None, registry=None) -> list[tuple[str, RunResult]]:
    """Run every ``[[variant]]`` of an ablation file, each into ``<ablation run dir>/<variant name>/``.

    A variant that fails does not stop the others: its result has ``metrics = {"failed": True, "error": "..."}``
    (see :func:`failed_result`) and ``comparison.json`` records the error. Ctrl-C still stops the ablation.
    """
    from .pipeline import run
    from .report import comparison_rows
    from .rundir import make_run_dir, make_variant_dir, write_json

    variants = load_ablation(path, overrides=overrides, registry=registry)
    first = variants[0].config.pipeline.run
    base = make_run_dir(first.output_dir, Path(path).stem)
    results: list[tuple[str, RunResult]] = []
    for v in variants:
        vdir = make_variant_dir(base, v.name)
        try:
            res = run(v.config, run_dir=vdir, registry=registry,
                      overrides={**_normalise_overrides(overrides), **v.deltas})
        except Exception as exc:  # noqa: BLE001 - recorded in the table; the other variants still run
            LOG.error("ablation variant %r failed: %s: %s", v.name, type(exc).__name__, exc)
            res = failed_result(vdir, exc)
        results.append((v.name, res))
        write_json(base / "comparison.json", comparison_rows(results))
    return results


def failed_result(run_dir: Optional[Union[str, Path]], exc: BaseException) -> RunResult:
    """The :class:`RunResult` of a run that raised: no poses, ``metrics = {"failed": True, "error": ...}``."""
    import torch

    return RunResult(run_dir=str(run_dir) if run_dir is not None else None,
                     timestamps=torch.zeros(0, dtype=torch.float64), poses=torch.zeros(0, 7, dtype=torch.float64),
                     keyframe_indices=torch.zeros(0, dtype=torch.int64),
                     keyframe_poses=torch.zeros(0, 7, dtype=torch.float64),
                     metrics={"failed": True, "error": f"{type(exc).__name__}: {exc}"})


def _evaluate_with(run_dir: Path, gt: Union[str, Path], registry) -> dict[str, Any]:
    """:func:`evaluate_run_dir` with the ground truth in file ``gt`` written as the run's ``groundtruth.txt``."""
    from .evaluation.user_gt import load_user_groundtruth
    from .outputs.metrics import MetricsFile
    from .outputs.trajectory_io import write_tum

    if not (run_dir / "trajectory.txt").is_file():
        raise FileNotFoundError(f"{run_dir / 'trajectory.txt'} not found: without the run's trajectory there is "
                                "nothing to evaluate")
    ts, poses, what = load_user_groundtruth(gt, run_dir)
    write_tum(run_dir / "groundtruth.txt", ts, poses)
    metrics = evaluate_run_dir(run_dir, registry=registry)
    metrics.setdefault("evaluation_sources", {})["trajectory"] = f"{what}, written to groundtruth.txt"
    MetricsFile(run_dir / "metrics.json").update({"evaluation_sources": metrics["evaluation_sources"]})
    return metrics


def evaluate_run_dir(run_dir: Union[str, Path], registry=None, gt: Union[str, Path, None] = None) -> dict[str, Any]:
    """Recompute the metrics of a run directory from its own files (``groundtruth.txt``,
    ``groundtruth_loops.json``); the dataset named in its ``config.json`` is opened only for panoptic labels, and
    a dataset (or dataset plugin) that is gone is reported in ``evaluation_sources``, not an error.  ``gt``: a
    ground-truth trajectory file (TUM or KITTI poses, :mod:`pvslam_core.evaluation.user_gt`) that becomes the run's
    ``groundtruth.txt`` first (replacing one that is there)."""
    from .config import ConfigError, EvaluationSection, OutputsSection
    from .evaluation.run_eval import read_json_object
    from .run_outputs import evaluate_saved_run

    run_dir = Path(run_dir)
    if not (run_dir / "config.json").is_file():
        raise FileNotFoundError(f"{run_dir}: not a pvslam run directory (no config.json)")
    if gt is not None:
        return _evaluate_with(run_dir, gt, registry)
    timing = {}
    if (run_dir / "metrics.json").is_file():
        timing = read_json_object(run_dir / "metrics.json").get("timing", {})
    raw = read_json_object(run_dir / "config.json")
    if not (run_dir / "trajectory.txt").is_file():  # its metrics would be an earlier evaluation's, not this one's
        raise FileNotFoundError(f"{run_dir / 'trajectory.txt'} not found: without the run's trajectory there is "
                                "nothing to evaluate (metrics.json is left as it was)")
    dataset = raw.get("dataset") if isinstance(raw.get("dataset"), dict) else {}
    fed = str(dataset.get("plugin", "?")) == "none"  # a Tracker's run: frames were fed
    try:
        if fed:
            raise ConfigError("frames were fed through the streaming API (Tracker): there is no dataset to reopen")
        resolved = load_config(run_dir / "config.json", registry=registry)
    except ConfigError as exc:  # e.g. the dataset plugin is not installed here: evaluate from the run directory
        pcfg = PipelineConfig(evaluation=EvaluationSection.model_validate(raw.get("evaluation", {})),
                              outputs=OutputsSection.model_validate(raw.get("outputs", {})))
        pcfg.dataset.plugin = str(dataset.get("plugin", "?"))
        why = str(exc) if fed else f"the run's config no longer resolves here: {exc}"
        return evaluate_saved_run(run_dir, None, timing, registry=registry, pcfg=pcfg, dataset_error=why)
    return evaluate_saved_run(run_dir, resolved, timing, registry=registry)
