"""Recompute the metrics of a run directory from its files (no dataset, no config needed).

Reads (see ``pvslam_core/outputs`` for the layout):

* ``trajectory.txt`` (TUM, every input frame) and ``groundtruth.txt`` (TUM) -> ``ate`` and ``rpe``
  (evo; Sim(3) alignment by default: monocular scale is unobservable), plus ``ate_keyframes`` from
  ``keyframes.txt`` when present, and ``ate_segments`` (each part aligned on its own) where ``metrics.json``'s
  ``tracking.scale_gaps`` holds a turn wider than the view; plots ``plots/trajectory_top.png`` and
  ``plots/ate_over_time.png``;
* ``loops.json`` + ground-truth revisit pairs (given by the caller) -> ``loops`` (precision / recall);
* ``panoptic/`` (PNG + ``segments.json``) + ground-truth panoptic frames (given by the caller) -> ``panoptic``
  (PQ and VPQ).

The results are merged into ``metrics.json`` (atomically; keys the pipeline wrote before, e.g. timing, are
kept). A section that cannot be computed records ``{"error": "..."}`` instead of failing the others; trajectory
metrics that cannot be computed any more (no ground truth or no trajectory) are removed, never left from an earlier
evaluation.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np

LOG = logging.getLogger("pvslam")

__all__ = ["evaluate_run", "read_json_object"]

#: the keys of metrics.json that :func:`_trajectory_metrics` computes from trajectory.txt and the ground truth
TRAJECTORY_KEYS = ("ate", "ate_segments", "rpe", "ate_keyframes")


def read_json_object(path: str | os.PathLike) -> dict:
    """A run file that must hold a JSON object (``config.json``, ``metrics.json``); :class:`ValueError` naming the
    file when it is not valid JSON or holds another JSON value."""
    import json

    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a UTF-8 text file ({e})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, found a JSON {type(data).__name__}")
    return data


def _load_gt_trajectory(run_dir: Path, gt: Any):
    from pvslam_core.outputs.trajectory_io import read_tum

    if gt is None:
        p = run_dir / "groundtruth.txt"
        return read_tum(p) if p.is_file() else None
    if isinstance(gt, (str, os.PathLike)):
        return read_tum(gt)
    ts, poses = gt
    return np.asarray(ts, dtype=np.float64), np.asarray(poses, dtype=np.float64)


def _scale_cuts(run_dir: Path) -> list[float]:
    """Where the run says its map's scale was not observed across a turn wider than the view (``metrics.json``:
    ``tracking.scale_gaps`` with ``beyond_fov``, :mod:`pvslam_core.slam.scale_gaps`): the gaps' first timestamps."""
    path = run_dir / "metrics.json"
    if not path.is_file():
        return []
    from pvslam_core.outputs.metrics import read_json

    try:
        gaps = read_json(path).get("tracking", {}).get("scale_gaps", [])
        return [float(g["first_time"]) for g in gaps if g.get("beyond_fov")]
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        LOG.warning("%s: tracking.scale_gaps not read (%s); no ate_segments", path, e)
        return []


def _panoptic_sequence(frames: Any) -> dict[int, Any]:
    """``{frame_index: segmentation}`` from a dict or a list indexed by frame."""
    if frames is None:
        return {}
    if isinstance(frames, Mapping):
        return {int(k): v for k, v in frames.items() if v is not None}
    return {i: v for i, v in enumerate(frames) if v is not None}


def evaluate_run(
    run_dir: str | os.PathLike,
    gt: Any = None,
    *,
    panoptic_gt: Any = None,
    loop_gt: Optional[Sequence[tuple[int, int]]] = None,
    categories: Any = None,
    align: str = "sim3",
    max_diff: float = 0.01,
    rpe_delta: int = 1,
    loop_tolerance: int = 5,
    vpq_ks: Sequence[int] = (0, 5, 10, 15),
    plots: bool = True,
    write: bool = True,
) -> dict:
    """Metrics of the run in ``run_dir``; merged into ``run_dir/metrics.json`` unless ``write=False``.

    ``gt``: the ground-truth trajectory when it is not ``run_dir/groundtruth.txt`` -- a TUM path or a
    ``(timestamps, poses)`` tuple -- or a dict with any of ``trajectory``, ``panoptic``, ``loops``,
    ``categories`` (the same as the keyword arguments). ``panoptic_gt``: GT panoptic frames, a dict
    ``{frame_index: PanopticSegmentation or (ids, segments)}`` or a list indexed by frame; compared with the
    frames of ``run_dir/panoptic`` that have GT, in frame order (VPQ windows run over those frames).
    ``loop_gt``: GT revisit pairs ``(i, j)`` of input-frame indices. ``categories``: panoptic categories
    (default: those stored in ``panoptic/segments.json``).
    """
    from pvslam_core.outputs.metrics import MetricsFile

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run directory not found: {run_dir}")
    if isinstance(gt, Mapping):
        panoptic_gt = gt.get("panoptic", panoptic_gt)
        loop_gt = gt.get("loops", loop_gt)
        categories = gt.get("categories", categories)
        gt = gt.get("trajectory")
    out: dict[str, Any] = {}
    out.update(_trajectory_metrics(run_dir, gt, align, max_diff, rpe_delta, plots))
    out.update(_loop_metrics(run_dir, loop_gt, loop_tolerance))
    out.update(_panoptic_metrics(run_dir, panoptic_gt, categories, vpq_ks))
    if write:
        metrics = MetricsFile(run_dir / "metrics.json")
        stale = [k for k in TRAJECTORY_KEYS if k in metrics.data and k not in out]
        if stale:  # an earlier evaluation's numbers no longer describe files in the run directory
            LOG.warning("%s: %s removed: not computable now (no trajectory.txt or no ground truth)",
                        metrics.path, ", ".join(stale))
            metrics.data = {k: v for k, v in metrics.data.items() if k not in stale}
        metrics.update(out)
    return out


def _trajectory_metrics(run_dir: Path, gt: Any, align: str, max_diff: float, rpe_delta: int, plots: bool) -> dict:
    """``ate``, ``ate_segments``, ``rpe``, ``ate_keyframes`` (and the plots) against the ground-truth trajectory."""
    out: dict[str, Any] = {}
    est_path = run_dir / "trajectory.txt"
    try:
        gt_traj = _load_gt_trajectory(run_dir, gt)
    except Exception as e:  # a broken GT file
        gt_traj = None
        out["ate"] = {"error": str(e)}
    if gt_traj is None or not est_path.is_file():
        return out
    from pvslam_core.evaluation.trajectory import ate, ate_segments, rpe
    from pvslam_core.outputs.trajectory_io import read_tum

    gt_ts, gt_poses = gt_traj
    try:
        est_ts, est = read_tum(est_path)
        out["ate"] = ate(est_ts, est, gt_ts, gt_poses, align=align, max_diff=max_diff)
        cuts = _scale_cuts(run_dir)
        if cuts:
            out["ate_segments"] = ate_segments(est_ts, est, gt_ts, gt_poses, cuts, align=align, max_diff=max_diff)
        try:
            out["rpe"] = rpe(est_ts, est, gt_ts, gt_poses, delta=rpe_delta, align=align, max_diff=max_diff)
        except ValueError as e:
            out["rpe"] = {"error": str(e)}
        if plots:
            _trajectory_plots(run_dir, (est_ts, est), (gt_ts, gt_poses), align, max_diff, out["ate"]["rmse"])
    except ValueError as e:
        LOG.warning("ATE of %s not computed: %s", run_dir, e)
        out["ate"] = {"error": str(e)}
    kf_path = run_dir / "keyframes.txt"
    if kf_path.is_file():
        try:
            kts, kposes = read_tum(kf_path)
            out["ate_keyframes"] = ate(kts, kposes, gt_ts, gt_poses, align=align, max_diff=max_diff)
        except ValueError as e:
            out["ate_keyframes"] = {"error": str(e)}
    return out


def _trajectory_plots(run_dir: Path, est: tuple, gt: tuple, align: str, max_diff: float, rmse: float) -> None:
    """``plots/trajectory_top.png`` and ``plots/ate_over_time.png`` of the aligned trajectory."""
    from pvslam_core.evaluation.trajectory import aligned_positions
    from pvslam_core.outputs.plots import plot_error_over_time, plot_trajectory_top

    res = aligned_positions(*est, *gt, align=align, max_diff=max_diff)
    (run_dir / "plots").mkdir(exist_ok=True)
    plot_trajectory_top(run_dir / "plots" / "trajectory_top.png", res["est_xyz"], res["gt_xyz"],
                        res["errors"], title=f"ATE RMSE {rmse:.4g} m ({align})")
    plot_error_over_time(run_dir / "plots" / "ate_over_time.png", res["timestamps"], res["errors"])


def _loop_metrics(run_dir: Path, loop_gt: Optional[Sequence[tuple[int, int]]], tolerance: int) -> dict:
    """``loops``: precision / recall of ``loops.json`` against the ground-truth revisit pairs."""
    loops_path = run_dir / "loops.json"
    if loop_gt is None or not loops_path.is_file():
        return {}
    from pvslam_core.evaluation.loops import loop_precision_recall
    from pvslam_core.outputs.loops_io import loop_frame_pairs, read_loops

    try:
        detected = loop_frame_pairs(read_loops(loops_path))
        return {"loops": loop_precision_recall(detected, loop_gt, tolerance=tolerance)}
    except (ValueError, KeyError) as e:
        return {"loops": {"error": str(e)}}


def _panoptic_metrics(run_dir: Path, panoptic_gt: Any, categories: Any, vpq_ks: Sequence[int]) -> dict:
    """``panoptic``: PQ and VPQ of the frames of ``panoptic/`` that have ground truth, in frame order."""
    from pvslam_core.outputs.panoptic_png import has_segments

    pan_dir = run_dir / "panoptic"
    gt_frames = _panoptic_sequence(panoptic_gt)
    if not (gt_frames and has_segments(pan_dir)):
        return {}
    from pvslam_core.evaluation.panoptic import pq, vpq
    from pvslam_core.outputs.panoptic_png import load_panoptic_dir, read_segments_json

    try:
        preds = load_panoptic_dir(pan_dir, categories, frames=set(gt_frames))
        if categories is None:
            categories = read_segments_json(pan_dir).get("categories") or None
        if categories is None:
            raise ValueError("no panoptic categories: pass categories= or write them to segments.json")
        idx = sorted(set(preds) & set(gt_frames))
        if not idx:
            raise ValueError("no predicted panoptic frame has ground truth")
        prs = [_at_gt_size(preds[i], gt_frames[i]) for i in idx]
        gts = [gt_frames[i] for i in idx]
        r_pq = pq(prs, gts, categories)
        r_vpq = vpq(prs, gts, categories, ks=vpq_ks)
        return {"panoptic": {
            "num_frames": len(idx),
            "pq": r_pq["pq"], "sq": r_pq["sq"], "rq": r_pq["rq"],
            "pq_things": r_pq["things"]["pq"], "pq_stuff": r_pq["stuff"]["pq"],
            "vpq": r_vpq["vpq"], "vpq_things": r_vpq["vpq_things"], "vpq_stuff": r_vpq["vpq_stuff"],
            "pq_detail": r_pq,
            "vpq_detail": r_vpq,
        }}
    except (ValueError, KeyError, FileNotFoundError) as e:
        LOG.warning("panoptic metrics of %s not computed: %s", run_dir, e)
        return {"panoptic": {"error": str(e)}}


def _at_gt_size(pred: Any, gt: Any) -> Any:
    """The predicted segmentation resized (nearest) to its ground truth's size when they differ."""
    g_ids = gt.ids if hasattr(gt, "ids") else gt[0]
    if tuple(pred.ids.shape) == tuple(np.shape(g_ids)):
        return pred
    import torch.nn.functional as F

    h, w = np.shape(g_ids)
    ids = F.interpolate(pred.ids[None, None].double(), size=(h, w), mode="nearest")[0, 0].long()
    return type(pred)(ids=ids, segments=pred.segments)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m pvslam_core.evaluation.run_eval RUN_DIR [--gt groundtruth.txt] [--align sim3|se3|none]``."""
    import argparse
    import json

    ap = argparse.ArgumentParser(description="Recompute the trajectory metrics of a pvslam run directory.")
    ap.add_argument("run_dir")
    ap.add_argument("--gt", default=None, help="TUM ground truth (default: RUN_DIR/groundtruth.txt)")
    ap.add_argument("--align", default="sim3", choices=["sim3", "se3", "none"])
    ap.add_argument("--max-diff", type=float, default=0.01, help="timestamp association tolerance (s)")
    ap.add_argument("--no-plots", action="store_true")
    args = ap.parse_args(argv)
    if not (Path(args.run_dir) / "trajectory.txt").is_file():
        ap.error(f"{Path(args.run_dir) / 'trajectory.txt'} not found: nothing to evaluate")
    out = evaluate_run(args.run_dir, gt=args.gt, align=args.align, max_diff=args.max_diff, plots=not args.no_plots)
    from pvslam_core.outputs.metrics import to_jsonable

    print(json.dumps(to_jsonable({k: v for k, v in out.items() if k in ("ate", "rpe", "ate_keyframes")}), indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
