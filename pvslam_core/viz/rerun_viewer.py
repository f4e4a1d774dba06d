"""A live viewer on `rerun <https://rerun.io>`_: the pipeline's :class:`~pvslam_core.observer.RunObserver`.

What is logged (entity paths; the world frame is the first camera's, OpenCV axes: x right, y down, z forward)::

    world/camera                   Transform3D per frame: the current pose T_wc (timeline "frame" and "time")
    world/camera/image             Pinhole of the frames as processed
    world/camera/image/rgb         the frame (JPEG-encoded, every `image_every`-th frame)
    world/camera/image/panoptic    SegmentationImage of the panoptic categories (class colours from the categories)
    world/keyframes                keyframe centres, and world/keyframes/path their path (after each window BA)
    world/map/rgb/kf_<id>          each keyframe's depth as points coloured by the image...
    world/map/panoptic/kf_<id>     ...and by panoptic class (when there is a segmenter)
    world/loops                    one segment per accepted loop closure, between the two keyframes
    world/trajectory               the final trajectory (every frame, after the final BA)

Keyframe points are re-logged for the keyframes the window BA still moves (the newest ``window``) and for every
keyframe after a loop closure and at the end; far points (beyond ``depth_factor`` x the keyframe's median depth)
and depth discontinuities are left out, as in the saved clouds (:mod:`pvslam_core.outputs.cloud`).

Sinks: ``spawn`` starts (or connects to) a rerun viewer, ``save`` writes an ``.rrd`` file, both at once work;
with neither the recording stays in memory (:meth:`RerunViewer.memory_bytes`, for tests).  rerun is imported
here only; the core never imports this module unless a viewer is asked for.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from ..observer import KeyframeSnapshot, RunObserver
from ..types import Category, Frame, FrameResult, Intrinsics, LoopClosure, PanopticSegmentation, RunResult, SequenceInfo

LOG = logging.getLogger("pvslam")
FLUSH_TIMEOUT = 30.0  # seconds close() waits for a spawned viewer to take the data
INSTALL_HINT = "the viewer needs rerun: pip install 'pvslam[viz]' (or pip install rerun-sdk)"


def import_rerun():
    try:
        import rerun as rr
    except ImportError as exc:
        raise ImportError(INSTALL_HINT) from exc
    if not hasattr(rr.RecordingStream, "set_time"):  # the timeline API of rerun >= 0.23
        raise ImportError(f"rerun-sdk {getattr(rr, '__version__', '?')} is too old; {INSTALL_HINT}")
    return rr


def backproject(poses: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, depth_factor: Optional[float] = 3.0,
                edge_ratio: Optional[float] = 1.5) -> tuple[torch.Tensor, torch.Tensor]:
    """World points ``[K, h, w, 3]`` (float32) of keyframe depth and which to show ``[K, h, w]`` (valid depth,
    not far, not on a discontinuity)."""
    from ..geometry.lie import se3_act
    from ..outputs.cloud import edge_mask, far_mask

    d = disps.float()
    k, h, w = d.shape
    valid = torch.isfinite(d) & (d > 0)
    if depth_factor is not None:
        valid &= far_mask(d, depth_factor)
    if edge_ratio is not None:
        valid &= edge_mask(d, edge_ratio)
    fx, fy, cx, cy = (float(v) for v in intr.reshape(-1)[:4])
    gy, gx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                            indexing="ij")
    z = 1.0 / torch.where(valid, d, torch.ones_like(d)).double()
    xc = torch.stack([(gx - cx) / fx * z, (gy - cy) / fy * z, z], dim=-1)  # [K, h, w, 3] camera frame
    xw = se3_act(poses.double()[:, None, None, :], xc)
    return xw.float(), valid


def category_colors(categories: Sequence[Category]) -> dict[int, tuple[int, int, int]]:
    return {int(c.id): tuple(int(v) for v in c.color) for c in categories}


def category_map(seg: PanopticSegmentation) -> np.ndarray:
    """``uint16 [H, W]`` category id per pixel (0 = void)."""
    return seg.category_map().cpu().numpy().astype(np.uint16)


class RerunViewer(RunObserver):
    """Logs a run to rerun; see the module doc.  ``window``: newest keyframes re-logged after each window BA."""

    def __init__(self, spawn: bool = True, save: Optional[str | Path] = None, application_id: str = "pvslam",
                 image_every: int = 1, window: int = 10, depth_factor: Optional[float] = 3.0,
                 edge_ratio: Optional[float] = 1.5, jpeg_quality: int = 85):
        if spawn:
            from . import ViewerUnavailable, display_problem

            why = display_problem()
            if why is not None:
                raise ViewerUnavailable(f"the rerun viewer cannot open: {why}")
        rr = import_rerun()
        self.rr = rr
        self.rec = rr.RecordingStream(application_id)
        self.save_path = Path(save) if save is not None else None
        self.spawned = bool(spawn)
        self._memory = None
        if self.save_path is not None:
            self.save_path.parent.mkdir(parents=True, exist_ok=True)
        if spawn and self.save_path is not None:
            self.rec.spawn(connect=False)  # start the viewer, then stream to it and to the file
            self.rec.set_sinks(rr.GrpcSink(), rr.FileSink(str(self.save_path)))
        elif spawn:
            self.rec.spawn()
        elif self.save_path is not None:
            self.rec.save(str(self.save_path))
        else:
            self._memory = self.rec.memory_recording()
        self.image_every = max(1, int(image_every))
        self.window = max(1, int(window))
        self.depth_factor, self.edge_ratio = depth_factor, edge_ratio
        self.jpeg_quality = int(jpeg_quality)
        self.colors: dict[int, tuple[int, int, int]] = {}
        self._logged: set[int] = set()  # keyframe ids whose points are logged
        self._loops: list[tuple[int, int]] = []  # (kf_i, kf_j) stable ids
        self._pinhole: Optional[tuple] = None
        self._closed = False
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)

    # ---------------------------------------------------------------------------------------- primitives --
    def set_frame(self, index: int, timestamp: Optional[float] = None) -> None:
        self.rec.set_time("frame", sequence=int(index))
        if timestamp is not None:
            self.rec.set_time("time", duration=float(timestamp))

    def log_categories(self, categories: Sequence[Category]) -> None:
        rr = self.rr
        self.colors = category_colors(categories)
        if categories:
            ctx = rr.AnnotationContext([rr.AnnotationInfo(id=int(c.id), label=c.name, color=tuple(c.color))
                                        for c in categories])
            self.rec.log("world", ctx, static=True)

    def log_pinhole(self, intr: Intrinsics) -> None:
        key = (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height)
        if key == self._pinhole:
            return
        self._pinhole = key
        # pixel centres at integers (pvslam) vs at +0.5 (rerun): shift the principal point by half a pixel
        self.rec.log("world/camera/image", self.rr.Pinhole(focal_length=[intr.fx, intr.fy],
                                                          principal_point=[intr.cx + 0.5, intr.cy + 0.5],
                                                          width=intr.width, height=intr.height,
                                                          image_plane_distance=0.5), static=True)

    def log_camera(self, pose: Any) -> None:
        p = np.asarray(pose, dtype=np.float64).reshape(7)
        self.rec.log("world/camera", self.rr.Transform3D(translation=p[:3],
                                                         quaternion=self.rr.Quaternion(xyzw=p[3:])))

    def log_image(self, rgb_hwc: np.ndarray) -> None:
        import cv2

        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb_hwc[:, :, ::-1]),
                               [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if ok:
            self.rec.log("world/camera/image/rgb", self.rr.EncodedImage(contents=buf.tobytes(),
                                                                        media_type="image/jpeg"))

    def log_panoptic(self, class_map: np.ndarray) -> None:
        self.rec.log("world/camera/image/panoptic", self.rr.SegmentationImage(class_map, opacity=0.5))

    def log_points(self, path: str, points: np.ndarray, colors: Optional[np.ndarray] = None,
                   static: bool = False) -> None:
        self.rec.log(path, self.rr.Points3D(points, colors=colors, radii=self.rr.Radius.ui_points(1.5)),
                     static=static)

    def log_path(self, path: str, positions: np.ndarray, static: bool = False,
                 color: tuple[int, int, int] = (255, 200, 0)) -> None:
        if len(positions) >= 2:
            self.rec.log(path, self.rr.LineStrips3D([positions], colors=[color]), static=static)

    def log_segments(self, path: str, segments: np.ndarray, static: bool = False,
                     color: tuple[int, int, int] = (255, 0, 255)) -> None:
        """``segments [N, 2, 3]``: one line per pair of points (an empty array clears the entity's lines)."""
        self.rec.log(path, self.rr.LineStrips3D(list(segments), colors=[color] * len(segments)), static=static)

    # ---------------------------------------------------------------------------------------- RunObserver --
    def on_start(self, info: SequenceInfo, categories: Sequence[Category]) -> None:
        self.log_categories(categories)
        self.log_pinhole(info.intrinsics)

    def on_frame(self, frame: Frame, result: FrameResult, panoptic: Optional[PanopticSegmentation]) -> None:
        self.set_frame(frame.index, frame.timestamp)
        self.log_pinhole(frame.intrinsics)
        self.log_camera(result.pose.cpu())
        if frame.index % self.image_every == 0:
            self.log_image(frame.image_hwc())
            if panoptic is not None:
                self.log_panoptic(category_map(panoptic))

    def _log_keyframes(self, snap: KeyframeSnapshot, ids: Optional[set[int]] = None) -> None:
        """Points of the keyframes in ``ids`` (all when None); entities of keyframes gone from the map cleared."""
        rr = self.rr
        all_ids = [int(i) for i in snap.ids.tolist()]
        gone = self._logged - set(all_ids)
        for kf in sorted(gone):
            for kind in ("rgb", "panoptic"):
                self.rec.log(f"world/map/{kind}/kf_{kf}", rr.Clear(recursive=False))
        self._logged -= gone
        if not all_ids:
            return
        centres = snap.poses[:, :3].numpy()
        self.log_points("world/keyframes", centres, np.tile(np.array([[255, 80, 0]], np.uint8), (len(centres), 1)))
        self.log_path("world/keyframes/path", centres)
        sel = [k for k, i in enumerate(all_ids) if ids is None or i in ids]
        if not sel:
            return
        idx = torch.tensor(sel)
        pts, valid = backproject(snap.poses[idx], snap.disps[idx], snap.intrinsics, self.depth_factor,
                                 self.edge_ratio)
        for row, k in enumerate(sel):
            kf = all_ids[k]
            m = valid[row]
            p = pts[row][m].numpy()
            img = snap.images.get(kf)
            rgb = img.permute(1, 2, 0)[m].numpy() if img is not None else None
            self.log_points(f"world/map/rgb/kf_{kf}", p, rgb)
            seg = snap.segs.get(kf)
            if seg is not None:
                cls = seg.category_map()[m].numpy()
                cols = np.array([self.colors.get(int(c), (128, 128, 128)) for c in range(int(cls.max(initial=0)) + 1)],
                                np.uint8)
                self.log_points(f"world/map/panoptic/kf_{kf}", p, cols[cls])
            self._logged.add(kf)

    def on_keyframes(self, keyframes: KeyframeSnapshot) -> None:
        ids = keyframes.ids.tolist()
        self._log_keyframes(keyframes, set(int(i) for i in ids[-self.window:]))

    def _log_loops(self, snap: KeyframeSnapshot) -> None:
        where = {int(i): snap.poses[k, :3].numpy() for k, i in enumerate(snap.ids.tolist())}
        segs = [np.stack([where[a], where[b]]) for a, b in self._loops if a in where and b in where]
        self.log_segments("world/loops", np.asarray(segs, np.float32).reshape(-1, 2, 3))

    def on_loop(self, loop: LoopClosure, keyframes: KeyframeSnapshot) -> None:
        self._loops.append((int(loop.kf_i), int(loop.kf_j)))
        self._log_keyframes(keyframes)  # a loop moves every keyframe
        self._log_loops(keyframes)

    def on_finish(self, result: RunResult, keyframes: KeyframeSnapshot) -> None:
        if len(result.timestamps):
            self.set_frame(len(result.timestamps) - 1, float(result.timestamps[-1]))
        self._log_keyframes(keyframes)
        self._log_loops(keyframes)
        self.log_path("world/trajectory", result.poses[:, :3].numpy(), color=(0, 200, 255))

    # -------------------------------------------------------------------------------------------- closing --
    def close(self) -> None:
        """Flush everything to the sinks (the .rrd file is complete afterwards)."""
        if self._closed:
            return
        self._closed = True
        try:
            # a spawned viewer that never connected (its window could not open) must not hold the process forever
            self.rec.flush(timeout_sec=FLUSH_TIMEOUT) if self.spawned else self.rec.flush()
            if self.save_path is not None:
                self.rec.disconnect()
        except Exception as exc:  # noqa: BLE001 - e.g. the spawned viewer did not start, was closed or timed out
            from ..adapt import NOTICE

            NOTICE.warning("viewer: %s (the run's files are written; --viz-save FILE.rrd records the view "
                           "without a display)", str(exc).splitlines()[0])

    def memory_bytes(self) -> bytes:
        """The recording as .rrd bytes (only without ``spawn`` and ``save``)."""
        if self._memory is None:
            raise RuntimeError("this viewer writes to a viewer or a file, not to memory")
        self.rec.flush()
        return bytes(self._memory.drain_as_bytes())
