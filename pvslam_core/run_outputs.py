"""What a run writes into its directory, and the end-of-run / ``pvslam eval`` evaluation.

Trajectory files are rewritten atomically every ``run.checkpoint_every`` keyframes and whenever the run stops,
so an error or Ctrl-C keeps a valid trajectory of what was processed.  Layout: see ``pvslam_core/outputs``.

A file that cannot be written (full disk, permissions) does not stop the others of the same checkpoint: each
failure is logged with its path and recorded in ``metrics.json`` under ``write_errors`` (with ``partial: true``),
then :class:`OutputWriteError` names every file that failed.  ``groundtruth.txt`` and ``groundtruth_loops.json``
make the run directory self-contained: ``pvslam eval`` re-evaluates it without the dataset.
"""
from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import numpy as np
import torch

from .config import PipelineConfig, ResolvedConfig
from .evaluation.loops import pair_array, read_pairs_json
from .outputs.trajectory_io import TrajectoryWriter, write_tum
from .types import Category, Frame, PanopticSegmentation, SequenceInfo

if TYPE_CHECKING:  # pragma: no cover
    from .slam.map_state import MapSnapshot

LOG = logging.getLogger("pvslam")


class OutputWriteError(OSError):
    """One or more result files could not be written; the message names each file and why."""


def to_input_pixels(seg: PanopticSegmentation, info: SequenceInfo) -> PanopticSegmentation:
    """``seg`` (in the processed frames' pixels) in the input's own pixels when the reader resized or cropped."""
    if info.input_intrinsics is None:
        return seg
    from .outputs.keyframes_io import intrinsics_dict
    from .outputs.nerfstudio import upsample_nearest

    src, dst = info.intrinsics, info.input_intrinsics
    ids = upsample_nearest(seg.ids.cpu().numpy(),
                           intrinsics_dict(dst.fx, dst.fy, dst.cx, dst.cy, dst.width, dst.height),
                           intrinsics_dict(src.fx, src.fy, src.cx, src.cy, src.width, src.height))
    return replace(seg, ids=torch.from_numpy(ids), features=None)


class RunOutputs:
    def __init__(self, run_dir: Path, pcfg: PipelineConfig, info: SequenceInfo,
                 categories: Optional[list[Category]] = None):
        self.dir = Path(run_dir)
        self.cfg = pcfg
        self.info = info
        # the panoptic output's categories: the segmenter's when it declares them, else the dataset's
        self.categories = list(categories) if categories else list(info.categories)
        self.traj = TrajectoryWriter(self.dir / "trajectory.txt", fmt="tum")
        self.traj_kitti = (TrajectoryWriter(self.dir / "trajectory_kitti.txt", fmt="kitti")
                           if pcfg.outputs.trajectory_kitti else None)
        self.gt_ts: list[float] = []
        self.gt_poses: list[torch.Tensor] = []
        self.names: dict[int, str] = {}  # input-frame index -> source name (keyframes.json, exports)
        self.write_errors: dict[str, str] = {}  # path -> error, of every write that failed
        if info.loop_pairs is not None:  # archived runs re-evaluate loops without the dataset
            self._write("groundtruth_loops.json", _write_pairs, self.dir / "groundtruth_loops.json", info.loop_pairs,
                        info.source or info.name)
        self.pan_writer = None
        if pcfg.outputs.panoptic_png:
            from .outputs.panoptic_png import PanopticWriter

            # a journal line per frame, segments.json once at the end (see PanopticWriter)
            self.pan_writer = PanopticWriter(self.dir, categories=self.categories or None,
                                             vis=pcfg.outputs.panoptic_vis, flush_every=0, journal=True)
        self.behind = None  # the output thread: per-frame VPS and panoptic writes (see Pipeline.step)
        if pcfg.run.write_behind > 0:
            from .background import BackgroundWriter

            self.behind = BackgroundWriter(pcfg.run.write_behind, name="pvslam-output")

    def frame(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> None:
        self.names[frame.index] = frame.name
        if frame.gt_pose is not None:
            self.gt_ts.append(frame.timestamp)
            self.gt_poses.append(frame.gt_pose.double())

    def panoptic(self, frame: Frame, seg: PanopticSegmentation) -> None:
        if self.pan_writer is not None:
            if self.behind is not None:  # `seg` is this frame's own object: nothing changes it afterwards
                self.behind.submit(self.panoptic_now, frame, seg)
            else:
                self.panoptic_now(frame, seg)
            self._raise_write_errors()  # also the errors of writes finished in the background

    def panoptic_now(self, frame: Frame, seg: PanopticSegmentation) -> None:
        """Write this frame's panoptic PNG in the calling thread (a write error is recorded, see :meth:`_write`), in
        the input's own pixels (nearest id; 0 = void where the reader cropped the input)."""
        if self.pan_writer is not None:
            seg = to_input_pixels(seg, self.info)
            self._write(f"panoptic/{frame.index:06d}.png", self.pan_writer.write, frame.index, seg,
                        frame.name or None)

    def behind_submit(self, fn, *args) -> bool:
        """Run ``fn(*args)`` on the output thread, in order with the writes; False (nothing done) without one."""
        if self.behind is None:
            return False
        self.behind.submit(fn, *args)
        self._raise_write_errors()
        return True

    def drain(self) -> None:
        """Wait for the background writes (their write errors are then in ``write_errors``)."""
        if self.behind is not None:
            self.behind.drain()

    def checkpoint(self, snap: "MapSnapshot", frames_done: Optional[int] = None) -> None:
        """Rewrite the trajectory files from the map's snapshot (:meth:`~.slam.mapper.Mapper.snapshot`);
        ``frames_done``: only the first so many frames (a run stopped mid-frame keeps the frames it completed, so
        trajectory.txt, groundtruth.txt and the log agree)."""
        ts, poses = snap.timestamps, snap.poses
        if frames_done is not None:
            ts, poses = ts[:frames_done], poses[:frames_done]
        if len(ts) == 0:
            return
        from .outputs.loops_io import write_loops

        self.traj.update(ts.numpy(), poses.numpy())
        self._write("trajectory.txt", self.traj.flush)
        if self.traj_kitti is not None:
            self.traj_kitti.update(ts.numpy(), poses.numpy())
            self._write("trajectory_kitti.txt", self.traj_kitti.flush)
        kf = snap.keyframes
        if len(kf.ids):
            self._write("keyframes.txt", write_tum, self.dir / "keyframes.txt", kf.timestamps.numpy(),
                        kf.poses.numpy())
        if self.gt_ts:
            self._write("groundtruth.txt", write_tum, self.dir / "groundtruth.txt", np.array(self.gt_ts),
                        torch.stack(self.gt_poses).numpy())
        self._write("loops.json", write_loops, self.dir / "loops.json", snap.loops)
        self._raise_write_errors()

    def close(self, snap: "MapSnapshot", partial: bool = False, frames_done: Optional[int] = None) -> None:
        """Final files: segments.json and the final map's files (point clouds, keyframe depth: the writers of
        ``outputs/formats.py``'s ``MAP_WRITERS``, from the map's snapshot, which need not hold the trajectory);
        with ``partial`` a metrics.json that says the run stopped early. Write failures are collected as in
        :meth:`checkpoint`."""
        behind, self.behind = self.behind, None
        try:
            if behind is not None:
                behind.close()  # every queued frame is written before segments.json
        finally:
            if self.pan_writer is not None:
                self._write("panoptic/segments.json", self.pan_writer.close)
        kf = snap.keyframes
        if len(kf.ids) and kf.initialized:  # the final map's files (outputs/formats.py: MAP_WRITERS)
            from .outputs.formats import MAP_WRITERS, MapOutput

            # keyframes.json records the input's own camera: the exports write the input's frames at its size
            run = MapOutput(self.dir, kf, self.categories, self.cfg.outputs, self.info.input_intrinsics
                            or self.info.intrinsics, self.names)
            for w in MAP_WRITERS:
                if getattr(self.cfg.outputs, w.enabled):
                    self._write(w.file, w.load(), run)
        if partial or self.write_errors:
            done = snap.frames if frames_done is None else frames_done
            self._partial_metrics({"frames_written": done})
        self._raise_write_errors()

    # ---------------------------------------------------------------------------------- write failures --
    def _write(self, name: str, fn, *args):
        """``fn(*args)``; an OSError is logged with the file and recorded instead of raised (see the module doc)."""
        try:
            return fn(*args)
        except OSError as exc:
            path = exc.filename if isinstance(exc.filename, str) and exc.filename else str(self.dir / name)
            msg = exc.strerror or str(exc)
            self.write_errors[path] = msg
            LOG.error("could not write %s: %s", path, msg)
            return None

    def _partial_metrics(self, extra: Optional[dict] = None) -> None:
        """``metrics.json`` with ``partial: true`` and the write errors so far (merged into what it holds)."""
        from .outputs.metrics import MetricsFile

        path = self.dir / "metrics.json"
        try:
            MetricsFile(path).update({"partial": True, **(extra or {}),
                                      **({"write_errors": dict(self.write_errors)} if self.write_errors else {})})
        except (OSError, ValueError) as exc:
            msg = getattr(exc, "strerror", None) or str(exc)
            self.write_errors[str(path)] = msg
            LOG.error("could not write %s: %s", path, msg)

    def _raise_write_errors(self) -> None:
        if not self.write_errors:
            return
        self._partial_metrics()
        lines = [f"{p}: {m}" for p, m in dict(self.write_errors).items()]  # a copy: the writer thread may add
        raise OutputWriteError("could not write " + "; ".join(lines))

    def evaluate(self, timing: dict, dataset) -> dict[str, Any]:
        return evaluate_saved_run(self.dir, None, timing, dataset=dataset, pcfg=self.cfg)


def _write_json(path: Path, obj: Any) -> None:
    from .outputs.metrics import write_json_atomic

    write_json_atomic(path, obj)


def _write_pairs(path: Path, pairs, source: str) -> None:
    from .evaluation.loops import write_pairs_json
    from .outputs._atomic import atomic_open

    with atomic_open(path, "w", encoding="utf-8", newline="\n") as f:
        write_pairs_json(f, pairs, source=source)


def evaluate_saved_run(run_dir: Path, resolved: Optional[ResolvedConfig], timing: dict, registry=None,
                       dataset=None, pcfg: Optional[PipelineConfig] = None,
                       dataset_error: Optional[str] = None) -> dict[str, Any]:
    """Metrics of a run directory: ATE/RPE (evo), loop precision/recall, PQ/VPQ; writes ``metrics.json`` and plots.

    Ground truth comes from the run directory first -- ``groundtruth.txt`` (trajectory) and
    ``groundtruth_loops.json`` (revisit pairs) -- so an archived or copied run is re-evaluated without its dataset.
    The dataset (rebuilt from ``resolved`` when not given) is only opened for what the run directory cannot hold:
    panoptic labels, and the revisits of runs written before ``groundtruth_loops.json``.  A dataset that cannot be
    opened (moved, plugin not installed: ``dataset_error``) is not an error; ``evaluation_sources`` in the result
    says where each kind of ground truth came from.
    """
    from .evaluation.run_eval import evaluate_run
    from .outputs.metrics import MetricsFile

    run_dir = Path(run_dir)
    pcfg = pcfg or resolved.pipeline
    ecfg = pcfg.evaluation
    MetricsFile(run_dir / "metrics.json").update({"timing": timing})
    if not ecfg.enabled:
        return {"timing": timing}
    sources: dict[str, str] = {}
    loop_gt = None
    loops_file = run_dir / "groundtruth_loops.json"
    if loops_file.is_file():
        loop_gt = read_pairs_json(loops_file)
        sources["loops"] = "groundtruth_loops.json (run directory)"
    from .outputs.panoptic_png import has_segments

    has_pred_panoptic = has_segments(run_dir / "panoptic")  # segments.json, or the journal of a killed run
    if dataset is None and dataset_error is None and (loop_gt is None or has_pred_panoptic) and resolved is not None:
        dataset, dataset_error = _open_dataset(resolved, registry)
    info = dataset.info() if dataset is not None else None
    if dataset is not None:
        sources["dataset"] = f"used: {pcfg.dataset.plugin} ({info.source or info.name})"
    elif dataset_error is not None:
        sources["dataset"] = f"not available ({dataset_error})"
    else:
        sources["dataset"] = "not needed"
    if loop_gt is None and info is not None and info.loop_pairs is not None:
        loop_gt, sources["loops"] = info.loop_pairs, "dataset"
    sources.setdefault("loops", "none (no groundtruth_loops.json, no revisits from the dataset)")
    if loop_gt is not None:
        loop_gt = _revisits_run(loop_gt, run_dir)
    sources["trajectory"] = ("groundtruth.txt (run directory)" if (run_dir / "groundtruth.txt").is_file()
                             else "none (no groundtruth.txt in the run directory)")
    panoptic_gt = None
    if info is not None and info.has_gt_panoptic and has_pred_panoptic:
        panoptic_gt = {}
        for frame in dataset:  # int32 ids bound the memory; at most max_panoptic_frames frames
            if frame.gt_panoptic is not None:  # in the input's pixels, as the predicted PNGs are
                gt = to_input_pixels(frame.gt_panoptic, info)
                panoptic_gt[frame.index] = (gt.ids.numpy().astype(np.int32), gt.segments)
            if len(panoptic_gt) >= ecfg.max_panoptic_frames:
                break
    sources["panoptic"] = ("dataset" if panoptic_gt else
                           "none (" + ("no predicted panoptic/" if not has_pred_panoptic else
                                       "needs the dataset's labels") + ")")
    out = evaluate_run(
        run_dir,
        panoptic_gt=panoptic_gt,
        loop_gt=loop_gt,
        categories=list(info.categories) if info is not None and info.categories else None,
        align=ecfg.align, rpe_delta=ecfg.rpe_delta, loop_tolerance=ecfg.loop_tolerance,
        vpq_ks=tuple(ecfg.vpq_ks), plots=pcfg.outputs.plots,
    )
    MetricsFile(run_dir / "metrics.json").update({"evaluation_sources": sources})
    return {"timing": timing, **out, "evaluation_sources": sources}


def _revisits_run(pairs, run_dir: Path) -> np.ndarray:
    """The ground-truth revisit pairs among the frames the run processed (``trajectory.txt``'s rows): a run stopped
    early (``run.max_frames``, an error) has no true loop at the frames it never reached, so its recall is not 0."""
    from .outputs.trajectory_io import read_tum

    pairs = pair_array(pairs)
    try:
        n = len(read_tum(run_dir / "trajectory.txt")[0])
    except (OSError, ValueError):
        return pairs
    return pairs[pairs.max(1) < n] if len(pairs) else pairs


def _open_dataset(resolved: ResolvedConfig, registry=None):
    """``(dataset, None)``, or ``(None, why)`` when the run's dataset cannot be opened any more."""
    from .interfaces import BuildContext
    from .registry import get_registry

    try:
        spec = (registry or get_registry()).get("dataset", resolved.pipeline.dataset.plugin)
        return spec.factory(resolved.models["dataset"], BuildContext(device=torch.device("cpu"))), None
    except Exception as exc:  # noqa: BLE001 - any failure to open it means: evaluate from the run directory
        return None, f"{type(exc).__name__}: {exc}"
