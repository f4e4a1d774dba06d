"""``pvslam export RUN_DIR --format colmap``: a COLMAP text model ``cameras.txt``, ``images.txt``, ``points3D.txt``
(camera and pixel conventions: :mod:`.export`).

One PINHOLE/OPENCV camera, one image per keyframe, one 3D point per point of ``cloud_rgb.ply``.  A point comes from
the depth of the keyframe named by its ``frame_index`` and is observed there.  Tracks are multi-view where the map
knows the correspondence: the point is also observed by each keyframe ``j`` paired with its keyframe -- the
:data:`NEIGHBOURS` nearest keyframes in time on each side and the loop closures of ``loops.json`` (the run does not
store the frame graph's edges) -- when it projects in front of ``j`` and inside its image, at the depth ``j``
estimated there (``j``'s inverse depth sampled bilinearly; relative difference under :data:`CONSISTENCY`).

The 2D points are the points' exact projections: the map has no keypoint measurements, so ``ERROR`` is 0.  Every
track entry ``(IMAGE_ID, POINT2D_IDX)`` is the entry of that image's ``POINTS2D`` that names the point back.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ._atomic import atomic_write_text
from .cloud import CONSISTENCY as _CLOUD_CONSISTENCY
from .cloud import NEIGHBOURS as _CLOUD_NEIGHBOURS
from .export import _cloud, _image_name, colmap_pose, project, to_corner_pixels

LOG = logging.getLogger("pvslam")
__all__ = ["export_colmap", "keyframe_pairs", "observations", "NEIGHBOURS", "CONSISTENCY"]

#: keyframes paired in time on each side of a keyframe: those the cloud's multi-view filter checked each point in
NEIGHBOURS = _CLOUD_NEIGHBOURS
#: relative depth difference under which a keyframe's own depth confirms a point: the cloud filter's agreement test
CONSISTENCY = _CLOUD_CONSISTENCY


def _colmap_camera(intr: dict) -> tuple[str, list[float]]:
    fx, fy = intr["fx"], intr["fy"]
    cx, cy = to_corner_pixels([intr["cx"], intr["cy"]])
    dist = list(intr.get("dist", []))
    if not any(dist):
        return "PINHOLE", [fx, fy, cx, cy]
    if len(dist) == 4:
        return "OPENCV", [fx, fy, cx, cy, *dist]
    if len(dist) in (5, 8):  # OpenCV (k1, k2, p1, p2, k3[, k4, k5, k6]) = COLMAP FULL_OPENCV's order
        return "FULL_OPENCV", [fx, fy, cx, cy, *(dist + [0.0] * (8 - len(dist)))]
    raise ValueError(f"{len(dist)} distortion coefficients have no COLMAP camera model")


def _loop_frames(run_dir: Path) -> list[tuple[int, int]]:
    """Input-frame pairs of the run's loop closures (``loops.json``; none when absent or unreadable)."""
    from .loops_io import loop_frame_pairs, read_loops

    path = run_dir / "loops.json"
    if not path.is_file():
        return []
    try:
        return loop_frame_pairs(read_loops(path))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        LOG.warning("%s cannot be read (%s: %s): COLMAP tracks pair keyframes in time only", path,
                    type(exc).__name__, exc)
        return []


def keyframe_pairs(frame_index: Any, loop_frames: Iterable[tuple[int, int]] = (),
                   neighbours: int = NEIGHBOURS) -> list[list[int]]:
    """Per keyframe (position in ``frame_index``) the positions of the keyframes paired with it: ``neighbours`` on
    each side in time, plus both ends of each loop ``(frame_i, frame_j)`` whose frames are keyframes."""
    k = len(frame_index)
    pos = {int(f): n for n, f in enumerate(np.asarray(frame_index).reshape(-1).tolist())}
    pairs = [{m for m in range(n - neighbours, n + neighbours + 1) if 0 <= m < k and m != n} for n in range(k)]
    for a, b in loop_frames:
        i, j = pos.get(int(a)), pos.get(int(b))
        if i is not None and j is not None and i != j:
            pairs[i].add(j)
            pairs[j].add(i)
    return [sorted(p) for p in pairs]


def _sample_inverse_depth(inv: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear ``inv [h, w]`` at ``(u, v)`` (pixel centres at integers; clamped to the map's border pixels);
    NaN where a tap has no depth (0)."""
    h, w = inv.shape
    uc, vc = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
    u0, v0 = np.floor(uc).astype(np.int64), np.floor(vc).astype(np.int64)
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    a, b = uc - u0, vc - v0
    taps = (inv[v0, u0], inv[v0, u1], inv[v1, u0], inv[v1, u1])
    val = (1 - a) * (1 - b) * taps[0] + a * (1 - b) * taps[1] + (1 - a) * b * taps[2] + a * b * taps[3]
    return np.where(np.all(np.stack(taps) > 0, axis=0), val, np.nan)


def _seen_by(points: np.ndarray, pose: np.ndarray, inv_depth: np.ndarray, intr: dict, dintr: dict
             ) -> tuple[np.ndarray, np.ndarray]:
    """Which ``points`` keyframe (``pose``, ``inv_depth`` at ``dintr``) sees inside its image at its own depth:
    ``(ok [N], uv [N, 2] pvslam image pixels)``."""
    uv, z = project(points, pose, intr["fx"], intr["fy"], intr["cx"], intr["cy"])
    uvd, _ = project(points, pose, dintr["fx"], dintr["fy"], dintr["cx"], dintr["cy"])
    with np.errstate(invalid="ignore", divide="ignore"):
        inside = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < intr["width"] - 0.5) \
            & (uv[:, 1] >= -0.5) & (uv[:, 1] < intr["height"] - 0.5)
        d_point = np.where(inside, 1.0 / z, np.nan)
        d_map = _sample_inverse_depth(inv_depth, np.nan_to_num(uvd[:, 0]), np.nan_to_num(uvd[:, 1]))
        agree = np.abs(d_point - d_map) < CONSISTENCY * np.maximum(d_point, d_map)
    return inside & agree, uv


def observations(points: np.ndarray, src: np.ndarray, kf: dict, pairs: list[list[int]]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every observation ``(image [M] keyframe position, point [M] index in points, uv [M, 2] pvslam pixels)``: a
    point in its own keyframe (``src``: that keyframe's input-frame index) when in front of it, and in each keyframe
    of ``pairs`` that sees it at its own depth (:func:`_seen_by`)."""
    intr, dintr = kf["intrinsics"]["image"], kf["intrinsics"]["depth"]
    depth = np.asarray(kf["depth"], np.float64)
    good = np.isfinite(depth) & (depth > 0)
    inv = np.where(good, 1.0 / np.where(good, depth, 1.0), 0.0)
    by_src = np.argsort(src, kind="stable")  # each keyframe's points, in file order
    image, point, uv = [], [], []
    for n, f in enumerate(np.asarray(kf["frame_index"]).tolist()):  # vectorised per keyframe and pair
        sel = by_src[np.searchsorted(src, f, sorter=by_src):np.searchsorted(src, f, "right", sorter=by_src)]
        if not len(sel):
            continue
        own, z = project(points[sel], kf["poses"][n], intr["fx"], intr["fy"], intr["cx"], intr["cy"])
        sel, own = sel[z > 0], own[z > 0]
        image.append(np.full(len(sel), n))
        point.append(sel)
        uv.append(own)
        for m in pairs[n]:
            ok, uv_m = _seen_by(points[sel], kf["poses"][m], inv[m], intr, dintr)
            image.append(np.full(int(ok.sum()), m))
            point.append(sel[ok])
            uv.append(uv_m[ok])
    if not image:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
    return np.concatenate(image).astype(np.int64), np.concatenate(point).astype(np.int64), np.concatenate(uv)


def _write_cameras(out_dir: Path, intr: dict, model: str, params: list[float]) -> None:
    atomic_write_text(out_dir / "cameras.txt",
                      "# Camera list with one line of data per camera:\n"
                      "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n"
                      f"1 {model} {intr['width']} {intr['height']} " + " ".join(f"{v:.17g}" for v in params) + "\n")


def export_colmap(run_dir: Path, out_dir: Path, kf: dict) -> dict[str, Any]:
    """COLMAP text model of the run (see the module docstring)."""
    intr = kf["intrinsics"]["image"]
    model, params = _colmap_camera(intr)
    qvec, tvec = colmap_pose(kf["poses"])
    pts, cols, src = _cloud(run_dir)
    frames = np.asarray(kf["frame_index"]).tolist()
    if src is not None and len(pts):
        image, point, uv = observations(pts, src, kf, keyframe_pairs(frames, _loop_frames(run_dir)))
    else:
        image, point, uv = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
        if len(pts):
            LOG.warning("cloud_rgb.ply has no frame_index: points3D.txt gets points without tracks")
    keep = np.zeros(len(pts), bool)
    keep[point] = True
    if src is None:
        keep[:] = True
    # POINTS2D of each image: its observations in order; POINT2D_IDX = the position there
    order = np.argsort(image, kind="stable")
    image, point, uv = image[order], point[order], to_corner_pixels(uv[order])
    idx = np.arange(len(image)) - np.searchsorted(image, image)
    out_dir.mkdir(parents=True, exist_ok=True)
    _write_cameras(out_dir, intr, model, params)
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(frames)} (pvslam keyframes; world-to-camera poses)"]
    for n, f in enumerate(frames):
        q, t = qvec[n], tvec[n]
        lo, hi = np.searchsorted(image, [n, n + 1])
        lines.append(f"{n + 1} " + " ".join(f"{v:.17g}" for v in (*q, *t)) + f" 1 {_image_name(f)}")
        lines.append(" ".join(f"{u:.6f} {v:.6f} {k + 1}" for (u, v), k in zip(uv[lo:hi].tolist(),
                                                                              point[lo:hi].tolist())))
    atomic_write_text(out_dir / "images.txt", "\n".join(lines) + "\n")
    by_point = np.lexsort((image, point))  # each point's track, by image
    tp, ti, tx = point[by_point], image[by_point], idx[by_point]
    starts = np.searchsorted(tp, np.arange(len(pts) + 1))
    plines = ["# 3D point list with one line of data per point:",
              "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
              f"# Number of points: {int(keep.sum())}"]
    for k in np.nonzero(keep)[0].tolist():
        x, y, z = pts[k]
        r, g, b = cols[k]
        track = "".join(f" {i + 1} {j}" for i, j in zip(ti[starts[k]:starts[k + 1]].tolist(),
                                                         tx[starts[k]:starts[k + 1]].tolist()))
        plines.append(f"{k + 1} {x:.9g} {y:.9g} {z:.9g} {r} {g} {b} 0{track}")
    atomic_write_text(out_dir / "points3D.txt", "\n".join(plines) + "\n")
    lengths = np.diff(starts)[keep]
    return {"images": len(frames), "points": int(keep.sum()), "camera_model": model,
            "observations": len(image), "multi_view_points": int((lengths >= 2).sum())}
