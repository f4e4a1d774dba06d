"""``pvslam export RUN_DIR --format nerfstudio``: ``transforms.json`` (OpenGL camera-to-world matrices; conventions
in :mod:`.export`), per-keyframe depth ``depth/NNNNNN.png`` and the point cloud as ``sparse_pc.ply`` (nerfstudio's
seed points).

Depth PNGs are 16-bit at the image size: ``value x depth_unit_scale_factor`` is the z-depth in map units, 0 where
there is none.  The keyframe depth (stored at the bundle adjustment's resolution) is upsampled by nearest neighbour:
each image pixel takes the depth of the depth pixel it lies in, so no depth is invented between a foreground edge
and the background behind it (bilinear would), and pixels without depth stay 0 instead of blending into their
neighbours.

nerfstudio reads the unit from its own option (``nerfstudio-data --depth-unit-scale-factor``, default 1e-3 for
millimetre PNGs), not from ``transforms.json``; :func:`depth_unit_scale` picks it from the median depth (the default
for a monocular map, whose median depth pvslam's initialisation sets near 1), it goes into ``transforms.json`` and
the summary, with a warning when the option must be passed.  Depths that 16 bits cannot hold at that unit (far
beyond the median: sky at the disparity floor, divergent pixels) are written as 0 and counted in the summary.
"""
from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ._atomic import atomic_write_bytes
from .export import _image_name, nerfstudio_c2w, to_corner_pixels
from .metrics import write_json_atomic

LOG = logging.getLogger("pvslam")
__all__ = ["export_nerfstudio", "depth_unit_scale", "upsample_nearest"]

UINT16_MAX = 65535
#: nerfstudio's default depth_unit_scale_factor (depth PNGs in millimetres)
NERFSTUDIO_DEFAULT_SCALE = 1e-3


def depth_unit_scale(median_depth: float) -> float:
    """The depth PNGs' unit for a map of median depth ``m``: nerfstudio's default when its steps are at most a
    hundredth of ``m`` and ten times ``m`` fits 16 bits, else the power of ten nearest to ``m / 1000`` (steps of
    3e-4 to 3e-3 of ``m``, and 20 to 200 times ``m`` fits)."""
    m = float(median_depth)
    if not (np.isfinite(m) and m > 0):
        return NERFSTUDIO_DEFAULT_SCALE
    if NERFSTUDIO_DEFAULT_SCALE <= m / 100 and UINT16_MAX * NERFSTUDIO_DEFAULT_SCALE >= 10 * m:
        return NERFSTUDIO_DEFAULT_SCALE
    return float(f"1e{int(np.round(np.log10(m / 1000)))}")


def upsample_nearest(depth: np.ndarray, intr: dict, dintr: dict) -> np.ndarray:
    """``depth [h, w]`` (intrinsics ``dintr``) at the image size of ``intr``: each image pixel the depth of the depth
    pixel it lies in (pixel centres at integers), 0 where that pixel is outside the depth map."""
    h, w = depth.shape
    u = (np.arange(intr["width"]) - intr["cx"]) * (dintr["fx"] / intr["fx"]) + dintr["cx"]
    v = (np.arange(intr["height"]) - intr["cy"]) * (dintr["fy"] / intr["fy"]) + dintr["cy"]
    ui, vi = np.floor(u + 0.5).astype(np.int64), np.floor(v + 0.5).astype(np.int64)
    out = depth[np.clip(vi, 0, h - 1)][:, np.clip(ui, 0, w - 1)]
    out[(vi < 0) | (vi >= h), :] = 0
    out[:, (ui < 0) | (ui >= w)] = 0
    return out


def _write_depth_png(path: Path, depth: np.ndarray, scale: float) -> int:
    """Write ``depth`` (0 = none) in units of ``scale``; returns how many depths were beyond 16 bits (written 0)."""
    import cv2

    valid = np.isfinite(depth) & (depth > 0)
    counts = np.round(np.where(valid, depth, 0) / scale)
    beyond = valid & (counts > UINT16_MAX)
    counts = np.where(valid & ~beyond, np.maximum(counts, 1), 0)
    ok, buf = cv2.imencode(".png", counts.astype(np.uint16))
    if not ok:
        raise OSError(f"PNG encoding of {path.name} failed")
    atomic_write_bytes(path, buf.tobytes(), durable=False)
    return int(beyond.sum())


def export_nerfstudio(run_dir: Path, out_dir: Path, kf: dict) -> dict[str, Any]:
    """nerfstudio dataset of the run (see the module docstring)."""
    intr, dintr = kf["intrinsics"]["image"], kf["intrinsics"]["depth"]
    cx, cy = to_corner_pixels([intr["cx"], intr["cy"]])
    dist = list(intr.get("dist", [])) + [0.0] * 4
    c2w = nerfstudio_c2w(kf["poses"])
    depth = np.asarray(kf["depth"], np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    scale = depth_unit_scale(float(np.median(depth[valid])) if valid.any() else 0.0)
    (out_dir / "depth").mkdir(parents=True, exist_ok=True)
    frames, beyond = [], 0
    for n, f in enumerate(np.asarray(kf["frame_index"]).tolist()):
        name = f"{int(f):06d}.png"
        beyond += _write_depth_png(out_dir / "depth" / name,
                                   upsample_nearest(np.where(valid[n], depth[n], 0.0), intr, dintr), scale)
        frames.append({"file_path": f"images/{_image_name(f)}", "transform_matrix": c2w[n].tolist(),
                       "depth_file_path": f"depth/{name}", "colmap_im_id": n + 1})
    meta: dict[str, Any] = {
        "camera_model": "OPENCV", "fl_x": intr["fx"], "fl_y": intr["fy"], "cx": float(cx), "cy": float(cy),
        "w": intr["width"], "h": intr["height"], "k1": dist[0], "k2": dist[1], "p1": dist[2], "p2": dist[3],
        "depth_unit_scale_factor": scale, "frames": frames,
    }
    if len(intr.get("dist", [])) > 4 and any(intr["dist"][4:]):
        meta["k3"] = intr["dist"][4]
    if (run_dir / "cloud_rgb.ply").is_file():
        shutil.copyfile(run_dir / "cloud_rgb.ply", out_dir / "sparse_pc.ply")
        meta["ply_file_path"] = "sparse_pc.ply"
    write_json_atomic(out_dir / "transforms.json", meta)
    if scale != NERFSTUDIO_DEFAULT_SCALE:
        LOG.warning("depth PNGs are in units of %g map units (the map's median depth is far from 1): train with "
                    "nerfstudio-data --depth-unit-scale-factor %g", scale, scale)
    total = len(depth) * intr["width"] * intr["height"]
    if beyond:
        LOG.info("depth PNGs: %d of %d pixels are beyond %g map units (16 bits at the unit) and written as 0",
                 beyond, total, UINT16_MAX * scale)
    return {"images": len(frames), "depth": f"{intr['width']}x{intr['height']} 16-bit PNG",
            "depth_unit_scale_factor": scale, "depth_pixels_beyond_range": beyond}
