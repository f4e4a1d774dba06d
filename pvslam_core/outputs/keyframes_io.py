"""Per-keyframe depth maps with their intrinsics and poses: ``run_dir/keyframes/``.

Layout::

    keyframes/000012_depth.npy     float32 [h, w] z-depth (along the optical axis) of keyframe 12 (input-frame
                                   index), at the depth resolution, in map units; 0 = no depth
    keyframes/keyframes.json       {"format_version": 1,
                                    "intrinsics": {"image": {fx, fy, cx, cy, width, height, dist},
                                                   "depth": {fx, fy, cx, cy, width, height}},
                                    "keyframes": [{"frame_index", "timestamp", "name", "pose", "depth_file"}],
                                    "conventions": {...}}

``image`` is the input's own camera (native size, undistorted when the run undistorted), also when the pipeline
processed the frames at another size; ``depth`` is the depth maps' grid (the BA resolution of the processed frames).

Conventions (as everywhere in pvslam, :mod:`pvslam_core.types`): ``pose`` is T_wc ``[tx, ty, tz, qx, qy, qz, qw]``,
camera x right, y down, z forward (OpenCV), pixel centres at integer coordinates.  A monocular map's unit is
arbitrary but the same for depth and poses.  :mod:`pvslam_core.outputs.export` turns this into COLMAP and
nerfstudio models.
"""
from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ._atomic import atomic_write_bytes
from .metrics import read_json, write_json_atomic

__all__ = ["write_keyframes", "read_keyframes", "intrinsics_dict"]

FORMAT_VERSION = 1
CONVENTIONS = {
    "pose": "T_wc [tx, ty, tz, qx, qy, qz, qw]: camera-to-world, Hamilton quaternion scalar last",
    "camera": "OpenCV: x right, y down, z forward",
    "pixels": "pixel centres at integer coordinates (the top-left pixel's centre is (0, 0))",
    "depth": "z-depth in map units (monocular: the trajectory's arbitrary scale), 0 = unknown",
}


def intrinsics_dict(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                    dist: Sequence[float] = ()) -> dict[str, Any]:
    d = {"fx": float(fx), "fy": float(fy), "cx": float(cx), "cy": float(cy), "width": int(width),
         "height": int(height)}
    if dist:
        d["dist"] = [float(v) for v in dist]
    return d


def _np(x: Any, dtype=None) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def write_keyframes(run_dir: str | os.PathLike, frame_index: Any, timestamps: Any, poses_wc: Any, disps: Any,
                    depth_intrinsics: Any, image_intrinsics: Any, names: Optional[Sequence[str]] = None) -> Path:
    """Write ``keyframes/`` (see the module docstring). ``disps [K, h, w]`` inverse depth; ``depth_intrinsics``
    ``[fx, fy, cx, cy]`` at that resolution; ``image_intrinsics`` an :class:`~pvslam_core.types.Intrinsics` of the
    input frames. Depth files of keyframes no longer in the map are removed. Returns ``keyframes.json``'s path."""
    out = Path(run_dir) / "keyframes"
    out.mkdir(exist_ok=True)
    fi = _np(frame_index, np.int64).reshape(-1)
    ts = _np(timestamps, np.float64).reshape(-1)
    poses = _np(poses_wc, np.float64).reshape(-1, 7)
    d = _np(disps, np.float32)
    k, h, w = d.shape
    if not (len(fi) == len(ts) == len(poses) == k):
        raise ValueError(f"write_keyframes: {len(fi)} indices, {len(ts)} timestamps, {len(poses)} poses, {k} depths")
    good = np.isfinite(d) & (d > 0)
    depth = np.where(good, 1.0 / np.where(good, d, 1.0), 0.0).astype(np.float32)  # [K, h, w] z-depth
    fx, fy, cx, cy = (float(v) for v in _np(depth_intrinsics, np.float64).reshape(-1)[:4])
    ki = image_intrinsics
    entries = []
    for n in range(k):
        fname = f"{int(fi[n]):06d}_depth.npy"
        buf = io.BytesIO()
        np.save(buf, depth[n])
        atomic_write_bytes(out / fname, buf.getvalue(), durable=False)
        entries.append({"frame_index": int(fi[n]), "timestamp": float(ts[n]),
                        "name": (names[n] if names is not None else "") or "",
                        "pose": [float(v) for v in poses[n]], "depth_file": fname})
    keep = {e["depth_file"] for e in entries}
    for p in out.glob("*_depth.npy"):  # a keyframe removed since the last write
        if p.name not in keep:
            p.unlink()
    meta = {
        "format_version": FORMAT_VERSION,
        "intrinsics": {
            "image": intrinsics_dict(ki.fx, ki.fy, ki.cx, ki.cy, ki.width, ki.height, ki.dist),
            "depth": intrinsics_dict(fx, fy, cx, cy, w, h),
        },
        "keyframes": entries,
        "conventions": CONVENTIONS,
    }
    write_json_atomic(out / "keyframes.json", meta)
    return out / "keyframes.json"


def read_keyframes(run_dir: str | os.PathLike, load_depth: bool = True) -> dict[str, Any]:
    """``keyframes.json`` plus arrays: ``frame_index int64 [K]``, ``timestamps [K]``, ``poses float64 [K, 7]``,
    ``depth float32 [K, h, w]`` (with ``load_depth``), ``names``, ``intrinsics`` (the JSON's dict).

    A file without the layout's keys, or a ``depth_file`` that leads out of the run directory (``..``, an absolute
    path, a symbolic link), raises :class:`ValueError` naming the file, the keyframe and the key."""
    d = Path(run_dir) / "keyframes"
    path = d / "keyframes.json"
    try:
        meta = read_json(path)
    except ValueError as e:  # json.JSONDecodeError, UnicodeDecodeError
        raise ValueError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object, found a JSON {type(meta).__name__}")
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{path}: format_version {meta.get('format_version')!r}, this code reads {FORMAT_VERSION}")
    kfs, intr = meta.get("keyframes"), meta.get("intrinsics")
    if not isinstance(kfs, list) or not all(isinstance(e, dict) for e in kfs):
        raise ValueError(f"{path}: 'keyframes' is missing or not a list of objects")
    if not isinstance(intr, dict) or not all(isinstance(intr.get(k), dict) for k in ("image", "depth")):
        raise ValueError(f"{path}: 'intrinsics' must hold 'image' and 'depth' objects")
    for kind in ("image", "depth"):
        lack = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in intr[kind]]
        if lack:
            raise ValueError(f"{path}: intrinsics.{kind} lacks {', '.join(lack)}")
    try:
        out = {
            "frame_index": np.array([e["frame_index"] for e in kfs], dtype=np.int64),
            "timestamps": np.array([e["timestamp"] for e in kfs], dtype=np.float64),
            "poses": np.array([e["pose"] for e in kfs], dtype=np.float64).reshape(-1, 7),
            "names": [e.get("name", "") for e in kfs],
            "intrinsics": intr,
        }
        if load_depth:
            di = intr["depth"]
            out["depth"] = (np.stack([np.load(_depth_path(run_dir, d, e, n), allow_pickle=False)
                                      for n, e in enumerate(kfs)]) if kfs
                            else np.zeros((0, di["height"], di["width"]), np.float32))
    except KeyError as e:
        raise ValueError(f"{path}: a keyframe or the intrinsics lack the key {e.args[0]!r}") from None
    except (TypeError, ValueError, EOFError) as e:
        raise ValueError(f"{path}: {e}") from None
    return out


def _depth_path(run_dir: str | os.PathLike, d: Path, entry: dict, n: int) -> Path:
    """The depth file of keyframe ``n``, which must stay inside the run directory once resolved (symbolic links
    followed): ``keyframes.json`` is data, so a ``depth_file`` of ``../../etc/hostname`` is refused, not read."""
    name = entry["depth_file"]
    if not isinstance(name, str) or not name:
        raise ValueError(f"keyframe {n}: depth_file {name!r} is not a file name")
    root = Path(run_dir).resolve()
    p = (d / name).resolve()
    if not p.is_relative_to(root):
        raise ValueError(f"keyframe {n}: depth_file {name!r} leads out of the run directory {root} (to {p}); "
                         "refused")
    if not p.is_file():
        raise ValueError(f"keyframe {n}: depth_file {name!r} not found ({p})")
    return p


def write_run_keyframes(run) -> Path:
    """The run's ``keyframes/`` from its final map (``run``: :class:`.formats.MapOutput`; a line of
    ``MAP_WRITERS``)."""
    kf = run.keyframes
    fi = kf.frame_index
    return write_keyframes(run.dir, fi, kf.timestamps, kf.poses, kf.disps, kf.intrinsics, run.intrinsics,
                           [run.names.get(int(i), "") for i in fi.tolist()])
