"""``pvslam export RUN_DIR --format colmap|nerfstudio|tum-aligned``: a run for 3D reconstruction tools (the formats
are listed in :mod:`.formats`; the COLMAP and nerfstudio writers are :mod:`.colmap` and :mod:`.nerfstudio`).

Inputs (all in the run directory): ``keyframes/`` (poses, depth, intrinsics; :mod:`.keyframes_io`),
``cloud_rgb.ply`` (points with the ``frame_index`` of the keyframe that saw them), ``loops.json`` (keyframe pairs
of the COLMAP tracks), ``trajectory.txt`` and ``groundtruth.txt``.  The cameras are keyframes.json's image camera:
the input's own pixels (native size, undistorted when the run undistorted), whatever size the pipeline processed;
the images are re-read from the run's dataset at that size and written as ``images/NNNNNN.png`` (input-frame
index); without the dataset the models still reference those names.

Camera conventions -- every conversion happens in exactly one function below:

* pvslam: ``T_wc = [t, q_xyzw]`` camera-to-world; camera x right, y down, z forward (OpenCV); the centre of the
  top-left pixel is (0, 0).
* COLMAP (:func:`colmap_pose`): world-to-camera ``R_cw = R_wc^T``, ``t_cw = -R_wc^T t_wc``, quaternion
  ``QW QX QY QZ`` (scalar first); camera axes as OpenCV.  COLMAP puts the top-left pixel's centre at (0.5, 0.5),
  so ``cx, cy`` and 2D points get ``+0.5`` (:func:`to_corner_pixels`).
* nerfstudio (:func:`nerfstudio_c2w`): camera-to-world 4x4 in OpenGL camera axes (x right, y up, z back):
  ``c2w_gl = c2w_cv @ diag(1, -1, -1, 1)``; the world frame stays pvslam's (nerfstudio re-orients and rescales
  it itself).  Its rays go through pixel centres at ``i + 0.5``, so ``cx, cy`` get ``+0.5`` as for COLMAP.
* TUM (``tum-aligned``): the trajectory mapped by the Sim(3) (Umeyama, as for the ATE) that best aligns its
  positions to ``groundtruth.txt``: ``t' = s R t + T``, ``R' = R R_wc``.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ._atomic import atomic_write_bytes
from .formats import EXPORT_FORMATS
from .trajectory_io import pose_to_matrix

LOG = logging.getLogger("pvslam")
FORMATS = tuple(EXPORT_FORMATS)
__all__ = ["FORMATS", "export_run", "colmap_pose", "nerfstudio_c2w", "to_corner_pixels", "project"]


# ------------------------------------------------------------------------------------------ conventions --
def _rotmats(q_xyzw: np.ndarray) -> np.ndarray:
    """``[K, 3, 3]`` rotation matrices of quaternions ``[..., 4]`` (x, y, z, w)."""
    q = np.asarray(q_xyzw, np.float64).reshape(-1, 4)
    return pose_to_matrix(np.concatenate([np.zeros((len(q), 3)), q], axis=1))[:, :3, :3]


def colmap_pose(poses_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """pvslam T_wc ``[K, 7]`` -> COLMAP world-to-camera ``(qvec [K, 4] as QW QX QY QZ with QW >= 0, tvec [K, 3])``."""
    p = np.asarray(poses_wc, np.float64).reshape(-1, 7)
    R_cw = np.transpose(_rotmats(p[:, 3:]), (0, 2, 1))
    t_cw = -np.einsum("kij,kj->ki", R_cw, p[:, :3])
    q = p[:, 3:] / np.linalg.norm(p[:, 3:], axis=1, keepdims=True)
    q_wxyz = np.stack([q[:, 3], -q[:, 0], -q[:, 1], -q[:, 2]], axis=1)  # the conjugate: R_wc^T, scalar first
    q_wxyz *= np.where(q_wxyz[:, :1] < 0, -1.0, 1.0)  # q and -q are the same rotation; COLMAP writes QW >= 0
    return q_wxyz, t_cw


def nerfstudio_c2w(poses_wc: np.ndarray) -> np.ndarray:
    """pvslam T_wc ``[K, 7]`` (OpenCV camera axes) -> nerfstudio ``transform_matrix`` ``[K, 4, 4]`` (OpenGL axes)."""
    p = np.asarray(poses_wc, np.float64).reshape(-1, 7)
    m = np.tile(np.eye(4), (len(p), 1, 1))
    m[:, :3, :3] = _rotmats(p[:, 3:])
    m[:, :3, 3] = p[:, :3]
    return m @ np.diag([1.0, -1.0, -1.0, 1.0])  # camera y down -> up, z forward -> back


def to_corner_pixels(uv: np.ndarray) -> np.ndarray:
    """pvslam pixel coordinates (top-left pixel centre at 0) -> COLMAP / nerfstudio ones (centre at 0.5)."""
    return np.asarray(uv, np.float64) + 0.5


def project(points_w: np.ndarray, pose_wc: np.ndarray, fx: float, fy: float, cx: float, cy: float
            ) -> tuple[np.ndarray, np.ndarray]:
    """pvslam pinhole projection of world points ``[N, 3]`` into the camera ``pose_wc [7]``: ``(uv [N, 2], z [N])``."""
    R = _rotmats(np.asarray(pose_wc)[3:])[0]
    xc = (np.asarray(points_w, np.float64) - np.asarray(pose_wc)[:3]) @ R  # R^T (X - t), row-wise
    z = xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([fx * xc[:, 0] / z + cx, fy * xc[:, 1] / z + cy], axis=1)
    return uv, z


# --------------------------------------------------------------------------------------------- helpers --
def _image_name(frame_index: int) -> str:
    return f"{int(frame_index):06d}.png"


def _cloud(run_dir: Path) -> tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """Points, colours and per-point keyframe ``frame_index`` of ``cloud_rgb.ply`` (empty when absent)."""
    from .ply import read_ply

    path = run_dir / "cloud_rgb.ply"
    if not path.is_file():
        LOG.warning("%s not found: the export has cameras and poses but no 3D points", path)
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), None
    pts, cols, extra = read_ply(path)
    if cols is None:
        cols = np.full((len(pts), 3), 128, np.uint8)
    return pts, cols, extra.get("frame_index")


def _open_dataset_at(run_dir: Path, size: tuple[int, int], registry=None):
    """The run's dataset yielding frames of ``size``: the input's own pixels (no resize, no crop) or, for a run
    whose keyframes.json records the processed frames' camera, the frames as the pipeline saw them."""
    import torch

    from ..config import load_config
    from ..datasets.base import ReaderOptions
    from ..interfaces import BuildContext
    from ..registry import get_registry

    resolved = load_config(run_dir / "config.json", registry=registry)
    spec = (registry or get_registry()).get("dataset", resolved.pipeline.dataset.plugin)
    options = resolved.models["dataset"]
    tries = [options]
    if isinstance(options, ReaderOptions):
        tries.insert(0, options.model_copy(update={"resize": None, "max_pixels": None, "crop_multiple": 1}))
    found = []
    for opts in tries:
        dataset = spec.factory(opts, BuildContext(device=torch.device("cpu")))
        k = dataset.info().intrinsics
        if (int(k.width), int(k.height)) == tuple(size):
            return dataset
        found.append(f"{k.width}x{k.height}")
    raise ValueError(f"its frames are {' or '.join(found)}, not the {size[0]}x{size[1]} of keyframes.json")


def write_images(run_dir: Path, out_dir: Path, frame_indices: np.ndarray, registry=None,
                 size: Optional[tuple[int, int]] = None) -> Optional[str]:
    """Write the keyframes' images from the run's dataset at ``size`` (keyframes.json's image camera: the input's
    own pixels); returns why not, or None."""
    import cv2

    want = {int(i) for i in frame_indices}
    try:
        if size is None:
            from .keyframes_io import read_keyframes

            image = read_keyframes(run_dir)["intrinsics"]["image"]
            size = (int(image["width"]), int(image["height"]))
        dataset = _open_dataset_at(run_dir, size, registry)
    except Exception as exc:  # noqa: BLE001 - the export is still useful without images
        return f"the run's dataset cannot be opened ({type(exc).__name__}: {exc})"
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    for frame in dataset:
        if frame.index in want:
            ok, buf = cv2.imencode(".png", np.ascontiguousarray(frame.image_hwc()[..., ::-1]))  # RGB -> OpenCV's BGR
            if not ok:
                raise OSError(f"PNG encoding of frame {frame.index} failed")
            atomic_write_bytes(out_dir / "images" / _image_name(frame.index), buf.tobytes(), durable=False)
            want.discard(frame.index)
        if not want:
            break
    return f"frames {sorted(want)[:10]} not found in the dataset" if want else None


# -------------------------------------------------------------------------------------------- TUM aligned --
def export_tum_aligned(run_dir: Path, out_dir: Path, kf: Optional[dict] = None, align: str = "sim3") -> dict[str, Any]:
    """``trajectory_aligned.txt``: ``trajectory.txt`` mapped onto ``groundtruth.txt`` by the ATE's alignment."""
    from ..evaluation.trajectory import aligned_positions
    from .trajectory_io import read_tum, write_tum

    gt_path = run_dir / "groundtruth.txt"
    if not gt_path.is_file():
        raise FileNotFoundError(f"{gt_path}: tum-aligned needs the ground truth in the run directory")
    ts, poses = read_tum(run_dir / "trajectory.txt")
    gts, gposes = read_tum(gt_path)
    res = aligned_positions(ts, poses, gts, gposes, align=align)
    m = np.asarray(res["alignment"], np.float64)  # [4, 4] with s R in the top-left block
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    R = m[:3, :3] / s
    from scipy.spatial.transform import Rotation

    out = poses.copy()
    out[:, :3] = poses[:, :3] @ m[:3, :3].T + m[:3, 3]
    out[:, 3:] = (Rotation.from_matrix(R) * Rotation.from_quat(poses[:, 3:])).as_quat()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_tum(out_dir / "trajectory_aligned.txt", ts, out)
    return {"poses": len(ts), "scale": s, "align": align, "ate_rmse": res["stats"].get("rmse")}


# ---------------------------------------------------------------------------------------------- entry --
def export_run(run_dir: str | os.PathLike, fmt: str, out_dir: Optional[str | os.PathLike] = None,
               images: bool = True, registry=None) -> dict[str, Any]:
    """Export ``run_dir`` as ``fmt`` (one of :data:`FORMATS`) into ``out_dir`` (default ``RUN_DIR/export/FMT``).
    Returns a summary (what was written, and ``images_missing`` when the images could not be written)."""
    from .keyframes_io import read_keyframes

    run_dir = Path(run_dir)
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if not (run_dir / "trajectory.txt").is_file():
        raise FileNotFoundError(f"{run_dir}: not a pvslam run directory (no trajectory.txt)")
    out = Path(out_dir) if out_dir is not None else run_dir / "export" / fmt
    spec = EXPORT_FORMATS[fmt]
    if not spec.keyframes:
        return {"format": fmt, "out": str(out), **spec.load()(run_dir, out, None)}
    if not (run_dir / "keyframes" / "keyframes.json").is_file():
        raise FileNotFoundError(f"{run_dir / 'keyframes' / 'keyframes.json'} not found: the run was made without "
                                "outputs.keyframe_depth (or before it existed), so there are no keyframe cameras")
    kf = read_keyframes(run_dir)
    summary = {"format": fmt, "out": str(out), **spec.load()(run_dir, out, kf)}
    if images:
        size = (int(kf["intrinsics"]["image"]["width"]), int(kf["intrinsics"]["image"]["height"]))
        why = write_images(run_dir, out, kf["frame_index"], registry=registry, size=size)
        if why:
            LOG.warning("images not written: %s; the model names them images/NNNNNN.png (input-frame index) at "
                        "%dx%d", why, kf["intrinsics"]["image"]["width"], kf["intrinsics"]["image"]["height"])
            summary["images_missing"] = why
    return summary
