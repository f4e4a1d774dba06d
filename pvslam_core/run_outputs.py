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
from .outputs.trajectory_io import TrajectoryWriter, write_tum
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

    The trajectory ground truth is ``groundtruth.txt`` in the run directory; panoptic labels and revisit pairs
    come from the dataset, rebuilt from the run's config when not given.
    """
    from .evaluation.run_eval import evaluate_run
    from .outputs.metrics import MetricsFile

    run_dir = Path(run_dir)
    pcfg = pcfg or resolved.pipeline
    ecfg = pcfg.evaluation
    MetricsFile(run_dir / "metrics.json").update({"timing": timing})
    if not ecfg.enabled:
        return {"timing": timing}
    if dataset is None and resolved is not None:
        from .interfaces import BuildContext
        from .registry import get_registry

        spec = (registry or get_registry()).get("dataset", resolved.pipeline.dataset.plugin)
        dataset = spec.factory(resolved.models["dataset"], BuildContext(device=torch.device("cpu")))
    info = dataset.info() if dataset is not None else None
    panoptic_gt = None
    if info is not None and info.has_gt_panoptic and (run_dir / "panoptic" / "segments.json").is_file():
        panoptic_gt = {}
        for frame in dataset:  # int32 ids bound the memory; at most max_panoptic_frames frames
            if frame.gt_panoptic is not None:
                panoptic_gt[frame.index] = (frame.gt_panoptic.ids.numpy().astype(np.int32),
                                            frame.gt_panoptic.segments)
            if len(panoptic_gt) >= ecfg.max_panoptic_frames:
                break
    out = evaluate_run(
        run_dir,
        panoptic_gt=panoptic_gt,
        loop_gt=info.loop_pairs if info is not None else None,
        categories=list(info.categories) if info is not None and info.categories else None,
        align=ecfg.align, rpe_delta=ecfg.rpe_delta, loop_tolerance=ecfg.loop_tolerance,
        vpq_ks=tuple(ecfg.vpq_ks), plots=pcfg.outputs.plots,
    )
    return {"timing": timing, **out}
