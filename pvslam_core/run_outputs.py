"""What a run writes into its directory, and the end-of-run / ``pvslam eval`` evaluation.

Trajectory files are rewritten atomically every ``run.checkpoint_every`` keyframes and whenever the run stops,
so an error or Ctrl-C keeps a valid trajectory of what was processed.  Layout: see ``pvslam_core/outputs``.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from .config import PipelineConfig, ResolvedConfig
from .outputs.trajectory_io import TrajectoryWriter, read_tum, write_tum
from .types import Frame, PanopticSegmentation, SequenceInfo

LOG = logging.getLogger("pvslam")


class RunOutputs:
    def __init__(self, run_dir: Path, pcfg: PipelineConfig, info: SequenceInfo):
        self.dir = Path(run_dir)
        self.cfg = pcfg
        self.info = info
        self.traj = TrajectoryWriter(self.dir / "trajectory.txt", fmt="tum")
        self.traj_kitti = (TrajectoryWriter(self.dir / "trajectory_kitti.txt", fmt="kitti")
                           if pcfg.outputs.trajectory_kitti else None)
        self.gt_ts: list[float] = []
        self.gt_poses: list[torch.Tensor] = []
        self.pan_writer = None
        if pcfg.outputs.panoptic_png:
            from .outputs.panoptic_png import PanopticWriter

            self.pan_writer = PanopticWriter(self.dir, categories=list(info.categories) or None,
                                             vis=pcfg.outputs.panoptic_vis)

    def frame(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> None:
        if frame.gt_pose is not None:
            self.gt_ts.append(frame.timestamp)
            self.gt_poses.append(frame.gt_pose.double())

    def panoptic(self, frame: Frame, seg: PanopticSegmentation) -> None:
        if self.pan_writer is not None:
            self.pan_writer.write(frame.index, seg)

    def checkpoint(self, mapper) -> None:
        ts, poses = mapper.trajectory()
        if len(ts) == 0:
            return
        self.traj.update(ts.numpy(), poses.numpy())
        self.traj.flush()
        if self.traj_kitti is not None:
            self.traj_kitti.update(ts.numpy(), poses.numpy())
            self.traj_kitti.flush()
        g = mapper.graph
        if g.n:
            write_tum(self.dir / "keyframes.txt", g.timestamps.double().cpu().numpy(), g.poses.double().cpu().numpy())
        if self.gt_ts:
            write_tum(self.dir / "groundtruth.txt", np.array(self.gt_ts), torch.stack(self.gt_poses).numpy())
        loops = [{"frame_i": c.i, "frame_j": c.j, "score": c.score, "inliers": c.inliers} for c in mapper.loops]
        _write_json(self.dir / "loops.json", {"loops": loops})

    def close(self, mapper, partial: bool = False) -> None:
        if self.pan_writer is not None:
            self.pan_writer.close()
        g = mapper.graph
        if self.cfg.outputs.ply and g.n and mapper.initialized:
            from .outputs.ply import panoptic_point_cloud_from_keyframes, point_cloud_from_keyframes, write_ply

            poses, disps, intr = g.poses.double().cpu(), g.disps.float().cpu(), g.intrinsics.cpu()
            max_depth = self.cfg.outputs.ply_max_depth
            pts, cols = point_cloud_from_keyframes(poses, disps, intr, torch.stack(mapper.kf_images),
                                                   max_depth=max_depth)
            write_ply(self.dir / "cloud_rgb.ply", pts, cols)
            if all(s is not None for s in mapper.kf_segs) and self.info.categories:
                pts2, cols2, extra = panoptic_point_cloud_from_keyframes(
                    poses, disps, intr, mapper.kf_segs, list(self.info.categories), max_depth=max_depth)
                write_ply(self.dir / "cloud_panoptic.ply", pts2, cols2, extra=extra)
        if partial:
            _write_json(self.dir / "metrics.json", {"partial": True, "frames_written": len(mapper.anchors)})

    def evaluate(self, mapper, timing: dict, dataset) -> dict[str, Any]:
        return evaluate_saved_run(self.dir, None, timing, dataset=dataset, pcfg=self.cfg)


def _write_json(path: Path, obj: Any) -> None:
    from .outputs.metrics import write_json_atomic

    write_json_atomic(path, obj)


def evaluate_saved_run(run_dir: Path, resolved: Optional[ResolvedConfig], timing: dict, registry=None,
                       dataset=None, pcfg: Optional[PipelineConfig] = None) -> dict[str, Any]:
    """Metrics of a run directory: ATE/RPE (evo), loop precision/recall, PQ/VPQ; writes ``metrics.json`` and plots.

    Ground truth comes from ``groundtruth.txt`` in the run directory (trajectory) and from the dataset
    (panoptic labels, revisit pairs), which is rebuilt from the run's config when not given.
    """
    run_dir = Path(run_dir)
    pcfg = pcfg or resolved.pipeline
    ecfg = pcfg.evaluation
    metrics: dict[str, Any] = {"timing": timing}
    if not ecfg.enabled:
        _write_json(run_dir / "metrics.json", metrics)
        return metrics
    if dataset is None and resolved is not None:
        from .registry import get_registry
        from .interfaces import BuildContext

        spec = (registry or get_registry()).get("dataset", resolved.pipeline.dataset.plugin)
        dataset = spec.factory(resolved.models["dataset"], BuildContext(device=torch.device("cpu")))
    est_path, gt_path = run_dir / "trajectory.txt", run_dir / "groundtruth.txt"
    if est_path.is_file() and gt_path.is_file():
        from .evaluation.trajectory import aligned_positions, ate, rpe

        est_ts, est = read_tum(est_path)
        gt_ts, gt = read_tum(gt_path)
        try:
            metrics["ate"] = {"align": ecfg.align, **ate(est_ts, est, gt_ts, gt, align=ecfg.align)}
            metrics["rpe"] = rpe(est_ts, est, gt_ts, gt, delta=ecfg.rpe_delta, align=ecfg.align)
            if pcfg.outputs.plots:
                _plots(run_dir, est_ts, est, gt_ts, gt, ecfg.align)
        except ValueError as exc:  # e.g. a degenerate (static) estimate cannot be Sim(3)-aligned
            LOG.warning("trajectory evaluation failed: %s", exc)
            metrics["ate"] = {"align": ecfg.align, "error": str(exc)}
    info = dataset.info() if dataset is not None else None
    if info is not None and info.loop_pairs is not None and (run_dir / "loops.json").is_file():
        from .evaluation.loops import loop_precision_recall

        loops = json.loads((run_dir / "loops.json").read_text())["loops"]
        detected = [(d["frame_i"], d["frame_j"]) for d in loops]
        metrics["loops"] = {"detected": len(detected),
                            **loop_precision_recall(detected, info.loop_pairs, tolerance=ecfg.loop_tolerance)}
    if info is not None and info.has_gt_panoptic and (run_dir / "panoptic" / "segments.json").is_file():
        metrics["panoptic"] = _panoptic_metrics(run_dir, dataset, info, ecfg)
    _write_json(run_dir / "metrics.json", metrics)
    return metrics


def _plots(run_dir: Path, est_ts, est, gt_ts, gt, align: str) -> None:
    from .evaluation.trajectory import aligned_positions
    from .outputs.plots import plot_error_over_time, plot_trajectory_top

    res = aligned_positions(est_ts, est, gt_ts, gt, align=align)
    (run_dir / "plots").mkdir(exist_ok=True)
    plot_trajectory_top(run_dir / "plots" / "trajectory_top.png", res["est_xyz"], res["gt_xyz"], res["errors"])
    plot_error_over_time(run_dir / "plots" / "ate_over_time.png", res["timestamps"], res["errors"])


def _panoptic_metrics(run_dir: Path, dataset, info: SequenceInfo, ecfg) -> dict[str, Any]:
    from .evaluation.panoptic import pq, vpq
    from .outputs.panoptic_png import load_panoptic_dir

    preds = load_panoptic_dir(run_dir / "panoptic")  # {frame index: PanopticSegmentation}
    gts, prs = [], []
    for frame in dataset:
        if frame.index not in preds or frame.gt_panoptic is None:
            continue
        gts.append((frame.gt_panoptic.ids.numpy().astype(np.int32), frame.gt_panoptic.segments))
        pred = preds.pop(frame.index)
        prs.append((pred.ids.numpy().astype(np.int32), pred.segments))
        if len(gts) >= ecfg.max_panoptic_frames:
            break
    if not gts:
        return {}
    cats = list(info.categories)
    out = {"frames": len(gts), **{k: v for k, v in pq(prs, gts, cats).items()}}
    v = vpq(prs, gts, cats, ks=tuple(ecfg.vpq_ks))
    out["VPQ"] = v.get("VPQ")
    out["vpq"] = v
    return out
