"""Point clouds: binary little-endian PLY writing/reading and back-projection of keyframe depth maps.

``write_ply`` builds one numpy structured array (x, y, z float32; red, green, blue uchar; optional extra scalar
properties) and writes header + raw bytes atomically: fast for millions of points.
"""
from __future__ import annotations

import os
from typing import Any, Optional, Sequence

import numpy as np

from ._atomic import atomic_open

__all__ = ["write_ply", "read_ply", "point_cloud_from_keyframes", "panoptic_point_cloud_from_keyframes"]

# numpy dtype -> PLY type name
_PLY_TYPES = {
    np.dtype("int8"): "char",
    np.dtype("uint8"): "uchar",
    np.dtype("int16"): "short",
    np.dtype("uint16"): "ushort",
    np.dtype("int32"): "int",
    np.dtype("uint32"): "uint",
    np.dtype("float32"): "float",
    np.dtype("float64"): "double",
}
_NP_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


def _np(x: Any, dtype=None) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def _extra_column(name: str, v: Any, n: int) -> np.ndarray:
    a = _np(v)
    if a.shape != (n,):
        raise ValueError(f"write_ply: extra property {name!r} must have shape ({n},), got {a.shape}")
    if a.dtype == np.bool_:
        a = a.astype(np.uint8)
    elif a.dtype == np.int64 or a.dtype == np.uint64:
        if a.size and (a.min() < np.iinfo(np.int32).min or a.max() > np.iinfo(np.int32).max):
            raise ValueError(f"write_ply: extra property {name!r} does not fit in int32 (PLY has no 64-bit ints)")
        a = a.astype(np.int32)
    elif a.dtype.newbyteorder("=") not in _PLY_TYPES:
        raise ValueError(f"write_ply: unsupported dtype {a.dtype} for property {name!r}")
    return a


def write_ply(
    path: str | os.PathLike,
    points: Any,
    colors: Optional[Any] = None,
    extra: Optional[dict[str, Any]] = None,
) -> int:
    """Write a binary little-endian PLY: ``points [N, 3]`` (stored float32), ``colors uint8 [N, 3]`` (optional),
    ``extra`` ``{name: [N] array}`` scalar properties (e.g. ``category_id``, ``instance_id``). Returns N."""
    pts = _np(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"write_ply: points must be [N, 3], got {pts.shape}")
    n = len(pts)
    fields: list[tuple[str, np.dtype]] = [("x", np.dtype("<f4")), ("y", np.dtype("<f4")), ("z", np.dtype("<f4"))]
    cols = None
    if colors is not None:
        cols = _np(colors)
        if cols.shape != (n, 3):
            raise ValueError(f"write_ply: colors must be [{n}, 3], got {cols.shape}")
        if cols.dtype != np.uint8:
            if np.issubdtype(cols.dtype, np.floating) and cols.size and cols.max() <= 1.0:
                cols = cols * 255.0
            cols = np.clip(np.round(cols), 0, 255).astype(np.uint8)
        fields += [("red", np.dtype("u1")), ("green", np.dtype("u1")), ("blue", np.dtype("u1"))]
    extra_cols: dict[str, np.ndarray] = {}
    for name, v in (extra or {}).items():
        if not name.isidentifier() or name in ("x", "y", "z", "red", "green", "blue"):
            raise ValueError(f"write_ply: bad extra property name {name!r}")
        a = _extra_column(name, v, n)
        extra_cols[name] = a
        fields.append((name, a.dtype.newbyteorder("<")))
    arr = np.empty(n, dtype=np.dtype(fields))
    arr["x"], arr["y"], arr["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if cols is not None:
        arr["red"], arr["green"], arr["blue"] = cols[:, 0], cols[:, 1], cols[:, 2]
    for name, a in extra_cols.items():
        arr[name] = a
    header = ["ply", "format binary_little_endian 1.0", "comment written by pvslam", f"element vertex {n}"]
    for name, dt in fields:
        header.append(f"property {_PLY_TYPES[dt.newbyteorder('=')]} {name}")
    header.append("end_header")
    with atomic_open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(arr.tobytes())
    return n


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, Optional[np.ndarray], dict[str, np.ndarray]]:
    """Read a PLY vertex element (binary little/big endian or ascii; scalar properties only):
    ``(points float32 [N, 3], colors uint8 [N, 3] or None, extra {name: [N]})``."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file")
        fmt, n, props, in_vertex = None, 0, [], False
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header without end_header")
            tok = line.decode("ascii").split()
            if not tok or tok[0] in ("comment", "obj_info"):
                continue
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                in_vertex = tok[1] == "vertex"
                if in_vertex:
                    n = int(tok[2])
                elif n == 0 and not props:
                    raise ValueError(f"{path}: only files whose first element is 'vertex' are supported")
            elif tok[0] == "property" and in_vertex:
                if tok[1] == "list":
                    raise ValueError(f"{path}: list properties on vertices are not supported")
                props.append((tok[2], _NP_TYPES[tok[1]]))
            elif tok[0] == "end_header":
                break
        if fmt == "ascii":
            data = np.loadtxt(f, max_rows=n, ndmin=2)
            arr = np.empty(n, dtype=[(p, t) for p, t in props])
            for k, (p, _) in enumerate(props):
                arr[p] = data[:, k]
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            dt = np.dtype([(p, order + t) for p, t in props])
            arr = np.frombuffer(f.read(dt.itemsize * n), dtype=dt, count=n)
    names = [p for p, _ in props]
    pts = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float32)
    cols = None
    if all(c in names for c in ("red", "green", "blue")):
        cols = np.stack([arr["red"], arr["green"], arr["blue"]], axis=1).astype(np.uint8)
    extra = {p: np.array(arr[p]) for p in names if p not in ("x", "y", "z", "red", "green", "blue")}
    return pts, cols, extra


# ----------------------------------------------------------------------------------------------------------------
# back-projection
# ----------------------------------------------------------------------------------------------------------------
def _rotmats(q):
    """``[K, 4]`` xyzw -> ``[K, 3, 3]`` (pvslam's lie module when available)."""
    import torch

    try:
        from pvslam_core.geometry.lie import quat_to_rotmat

        return quat_to_rotmat(q)
    except ImportError:  # pragma: no cover - the geometry module is part of pvslam
        q = q / q.norm(dim=-1, keepdim=True)
        x, y, z, w = q.unbind(-1)
        return torch.stack(
            [
                1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
            ],
            dim=-1,
        ).reshape(q.shape[:-1] + (3, 3))


def _backproject(poses_wc, disps, intr, max_depth, rel_max_depth, stride, mask):
    """World points ``[K, h', w', 3]`` (float64 torch) and validity ``[K, h', w']`` of strided keyframe pixels."""
    import torch

    poses = torch.as_tensor(_np(poses_wc, np.float64))
    d = torch.as_tensor(_np(disps, np.float64))
    if d.ndim == 2:
        d = d[None]
    if poses.ndim == 1:
        poses = poses[None]
    k, h, w = d.shape
    if poses.shape != (k, 7):
        raise ValueError(f"poses_wc must be [{k}, 7] for {k} depth maps, got {tuple(poses.shape)}")
    fx, fy, cx, cy = (float(v) for v in _np(intr, np.float64).reshape(-1)[:4])
    ys = torch.arange(0, h, stride, dtype=torch.float64)
    xs = torch.arange(0, w, stride, dtype=torch.float64)
    d = d[:, ::stride, ::stride]
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    valid = torch.isfinite(d) & (d > 0)
    z = torch.where(valid, 1.0 / torch.where(valid, d, torch.ones_like(d)), torch.zeros_like(d))
    if max_depth is not None:
        valid &= z <= max_depth
    elif rel_max_depth is not None:
        # Per keyframe: drop points farther than rel_max_depth x the median depth (sky, near-zero disparity).
        med = torch.nanmedian(torch.where(valid, z, torch.full_like(z, float("nan"))).flatten(1), dim=1).values
        valid &= z <= rel_max_depth * med[:, None, None]
    if mask is not None:
        m = torch.as_tensor(_np(mask)).bool()
        if m.ndim == 2:
            m = m[None]
        if m.shape != (k, h, w):
            raise ValueError(f"mask must be [{k}, {h}, {w}], got {tuple(m.shape)}")
        valid &= m[:, ::stride, ::stride]
    xc = torch.stack([(gx - cx) / fx * z, (gy - cy) / fy * z, z], dim=-1)  # [K, h', w', 3]
    rot = _rotmats(poses[:, 3:])  # [K, 3, 3]
    xw = torch.einsum("kij,kyxj->kyxi", rot, xc) + poses[:, None, None, :3]
    return xw, valid, (h, w)


def _resize_to(arr: np.ndarray, h: int, w: int, nearest: bool) -> np.ndarray:
    """Resize ``[K, C, H, W]`` or ``[K, H, W]`` to ``(h, w)``."""
    import torch
    import torch.nn.functional as F

    if arr.shape[-2:] == (h, w):
        return arr
    t = torch.as_tensor(arr)
    squeeze = t.ndim == 3
    if squeeze:
        t = t[:, None]
    if nearest:
        out = F.interpolate(t.double(), size=(h, w), mode="nearest").to(t.dtype)
    else:
        out = F.interpolate(t.double(), size=(h, w), mode="area").round().clamp(0, 255).to(t.dtype)
    if squeeze:
        out = out[:, 0]
    return out.numpy()


def point_cloud_from_keyframes(
    poses_wc: Any,
    disps: Any,
    intr: Any,
    images: Any,
    max_depth: Optional[float] = None,
    stride: int = 1,
    rel_max_depth: Optional[float] = 5.0,
    mask: Optional[Any] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project every keyframe's inverse depth with its pose into one coloured world point cloud.

    ``poses_wc [K, 7]`` T_wc, ``disps [K, h, w]`` inverse depth, ``intr [4]`` (fx, fy, cx, cy at the depth
    resolution), ``images uint8 [K, 3, H, W]`` (resized to ``h, w`` when needed). Invalid pixels (disparity
    <= 0 or not finite) are dropped, and far points: beyond ``max_depth`` when given, else beyond
    ``rel_max_depth`` x the keyframe's median depth (``None`` for both keeps every valid point). ``stride``
    subsamples pixels; ``mask [K, h, w]`` (bool) selects pixels (e.g. static ones).
    Returns ``points float32 [N, 3]``, ``colors uint8 [N, 3]``.
    """
    xw, valid, (h, w) = _backproject(poses_wc, disps, intr, max_depth, rel_max_depth, stride, mask)
    imgs = _np(images)
    if imgs.ndim == 3:
        imgs = imgs[None]
    if imgs.ndim != 4 or imgs.shape[1] != 3 or imgs.shape[0] != xw.shape[0]:
        raise ValueError(f"images must be uint8 [K, 3, H, W] with K={xw.shape[0]}, got {imgs.shape}")
    imgs = _resize_to(imgs, h, w, nearest=False)[:, :, ::stride, ::stride]
    v = valid.numpy()
    pts = xw.numpy()[v].astype(np.float32)
    cols = np.ascontiguousarray(imgs.transpose(0, 2, 3, 1))[v].astype(np.uint8)
    return pts, cols


def panoptic_point_cloud_from_keyframes(
    poses_wc: Any,
    disps: Any,
    intr: Any,
    panoptic: Sequence[Any],
    categories: Any,
    max_depth: Optional[float] = None,
    stride: int = 1,
    rel_max_depth: Optional[float] = 5.0,
    mask: Optional[Any] = None,
    keep_void: bool = False,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Like :func:`point_cloud_from_keyframes`, coloured by panoptic category (thing instances shaded distinctly,
    see :func:`pvslam_core.outputs.panoptic_png.colorize`). ``panoptic``: one
    :class:`~pvslam_core.types.PanopticSegmentation` per keyframe (nearest-resized to the depth resolution).
    Returns ``points, colors, extra`` with ``extra = {"category_id": int32 [N] (-1 void), "segment_id": int32 [N],
    "keyframe": int32 [N] (the point's keyframe, 0..K-1)}``
    (pass ``extra`` to :func:`write_ply`). Void pixels are dropped unless ``keep_void``.
    """
    from .panoptic_png import colorize

    xw, valid, (h, w) = _backproject(poses_wc, disps, intr, max_depth, rel_max_depth, stride, mask)
    if len(panoptic) != xw.shape[0]:
        raise ValueError(f"{len(panoptic)} panoptic frames for {xw.shape[0]} keyframes")
    ids_l, cats_l, cols_l = [], [], []
    for seg in panoptic:
        col = colorize(seg, categories).transpose(2, 0, 1)[None]  # [1, 3, H, W]
        ids = _np(seg.ids).astype(np.int64)[None]
        uniq, inv = np.unique(ids, return_inverse=True)
        seg_cat = {int(sg.id): int(sg.category_id) for sg in seg.segments}
        cat = np.array([seg_cat.get(int(i), -1) if i != 0 else -1 for i in uniq], dtype=np.int64)[inv.reshape(ids.shape)]
        cols_l.append(_resize_to(col, h, w, nearest=True)[0])
        ids_l.append(_resize_to(ids, h, w, nearest=True)[0])
        cats_l.append(_resize_to(cat, h, w, nearest=True)[0])
    cols = np.stack(cols_l)[:, :, ::stride, ::stride].transpose(0, 2, 3, 1)
    ids = np.stack(ids_l)[:, ::stride, ::stride]
    cats = np.stack(cats_l)[:, ::stride, ::stride]
    v = valid.numpy()
    if not keep_void:
        v &= ids != 0
    pts = xw.numpy()[v].astype(np.float32)
    extra = {"category_id": cats[v].astype(np.int32), "segment_id": ids[v].astype(np.int32),
             "keyframe": np.nonzero(v)[0].astype(np.int32)}
    return pts, np.ascontiguousarray(cols[v]).astype(np.uint8), extra
