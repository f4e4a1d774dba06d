"""Which keyframe depth pixels make a clean point cloud, and voxel downsampling.

A monocular map has an arbitrary scale, so every threshold here is relative (to a keyframe's median depth, to the
depths of neighbouring keyframes, to the map's median depth), never in metres:

* **far**: depth beyond ``depth_factor`` x the keyframe's median depth (sky, near-zero disparity, divergent BA);
* **edges**: pixels whose 3x3 neighbourhood spans a disparity ratio above ``edge_ratio`` -- the "flying pixels"
  that interpolated depth puts between a foreground object and the background behind it;
* **multi-view consistency** (DROID-SLAM's depth filter, the confidence test): a pixel is kept when its depth,
  moved into at least ``min_views`` of the ``neighbours`` keyframes on each side, agrees with the depth that
  keyframe itself estimated there within ``consistency`` (relative inverse depth).  Unstable depth (low flow
  confidence, moving objects, textureless sky) disagrees between keyframes and is dropped;
* **categories**: pixels of named panoptic categories (``sky`` by default) when segmentation is available.

All masks are computed for every keyframe at once (torch, ``[K, h, w]``).  Poses are T_wc ``[t, q_xyzw]``.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["CloudFilter", "clean_mask", "far_mask", "edge_mask", "consistency_count", "category_mask",
           "voxel_downsample", "median_depth", "write_clouds", "write_run_clouds"]

LOG = logging.getLogger("pvslam")


#: flying pixels: a 3x3 neighbourhood spanning a disparity ratio above this is a depth discontinuity
EDGE_RATIO = 1.5
#: multi-view consistency: keyframes checked on each side of a keyframe (DROID-SLAM's depth filter)
NEIGHBOURS = 2
#: multi-view consistency: relative inverse-depth difference under which two keyframes agree
CONSISTENCY = 0.05


@dataclass
class CloudFilter:
    """Parameters of :func:`clean_mask` (``None`` / 0 switches a test off); see the module docstring."""

    depth_factor: Optional[float] = 3.0
    edge_ratio: Optional[float] = EDGE_RATIO
    min_views: int = 1
    neighbours: int = NEIGHBOURS
    consistency: float = CONSISTENCY
    drop_categories: Sequence[str] = field(default_factory=lambda: ("sky",))

    @classmethod
    def from_outputs(cls, outputs: Any) -> "CloudFilter":
        """From the ``[outputs]`` config section (``ply_*`` keys; the other tests use this module's constants)."""
        return cls(depth_factor=outputs.ply_depth_factor, min_views=outputs.ply_min_views,
                   drop_categories=tuple(outputs.ply_drop_categories))


def _valid(disps: torch.Tensor) -> torch.Tensor:
    return torch.isfinite(disps) & (disps > 0)


def median_depth(disps: torch.Tensor) -> torch.Tensor:
    """Per-keyframe median depth ``[K]`` of valid pixels (NaN for a keyframe without any)."""
    z = torch.where(_valid(disps), 1.0 / disps.clamp_min(1e-12), torch.full_like(disps, float("nan")))
    return torch.nanmedian(z.flatten(1), dim=1).values


def far_mask(disps: torch.Tensor, factor: float) -> torch.Tensor:
    """``[K, h, w]`` True where depth <= ``factor`` x the keyframe's median depth (and the disparity is valid)."""
    # depth <= f * median  <=>  disp >= 1 / (f * median); a keyframe without valid pixels keeps nothing
    lim = 1.0 / (factor * median_depth(disps))
    return _valid(disps) & (disps >= torch.nan_to_num(lim, nan=float("inf"))[:, None, None])


def edge_mask(disps: torch.Tensor, ratio: float) -> torch.Tensor:
    """``[K, h, w]`` True away from depth discontinuities: max/min disparity of the 3x3 neighbourhood <= ratio."""
    d = torch.where(_valid(disps), disps, torch.zeros_like(disps))[:, None]
    hi = F.max_pool2d(d, 3, stride=1, padding=1)
    big = torch.where(d > 0, d, torch.full_like(d, float("inf")))
    lo = -F.max_pool2d(-big, 3, stride=1, padding=1)  # min over valid neighbours
    return ((hi <= ratio * lo) & (d > 0))[:, 0]


def consistency_count(poses_wc: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, neighbours: int = 2,
                      consistency: float = 0.05, chunk: int = 64) -> torch.Tensor:
    """``int [K, h, w]``: how many of the ``neighbours`` keyframes on each side see the pixel's 3D point at the
    depth they estimated themselves (relative inverse-depth difference < ``consistency``)."""
    k, h, w = disps.shape
    count = torch.zeros(k, h, w, dtype=torch.int64, device=disps.device)
    offs = [o for o in range(-neighbours, neighbours + 1) if o != 0]
    if not offs or k < 2:
        return count
    ii = torch.cat([torch.arange(k) for _ in offs])
    jj = torch.cat([torch.arange(k) + o for o in offs])
    keep = (jj >= 0) & (jj < k)
    ii, jj = ii[keep].to(disps.device), jj[keep].to(disps.device)
    d = disps.double()
    poses = poses_wc.double().to(d.device)
    for s in range(0, len(ii), chunk):  # chunks of pairs bound the memory on long runs
        ci, cj = ii[s:s + chunk], jj[s:s + chunk]
        count.index_add_(0, ci, _agree(poses, d, intr.double(), ci, cj, consistency).long())
    return count


def _agree(poses: torch.Tensor, d: torch.Tensor, intr: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
           consistency: float) -> torch.Tensor:
    """``bool [E, h, w]``: pixel of keyframe ``ii[e]`` lands inside keyframe ``jj[e]`` at that keyframe's depth."""
    from ..geometry.projective import edge_transforms, project_points

    h, w = d.shape[-2:]
    R, t = edge_transforms(poses, ii, jj)
    d_i = d[ii].reshape(len(ii), -1)
    out = project_points(R, t, d_i, intr, h, w, min_depth=1e-9)
    u, v = out["u"].reshape(-1, h, w), out["v"].reshape(-1, h, w)
    # the pixel's 3D point has depth Z / d_i in camera j (Z: the homogeneous depth), so inverse depth d_i / Z
    d_proj = (d_i / out["z"].clamp_min(1e-12)).reshape(-1, h, w)
    # keyframe j's own inverse depth there (bilinear; pixel centres at integers, hence align_corners=True)
    grid = torch.stack([u / max(w - 1, 1) * 2 - 1, v / max(h - 1, 1) * 2 - 1], dim=-1)
    d_j = F.grid_sample(d[jj][:, None], grid, mode="bilinear", padding_mode="zeros", align_corners=True)[:, 0]
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    agree = out["valid"].reshape(-1, h, w) & inside & (d_j > 0) & (d_proj > 0) & _valid(d[ii])
    return agree & ((d_proj - d_j).abs() < consistency * torch.maximum(d_proj, d_j))


def category_mask(segs: Sequence[Any], categories: Any, names: Sequence[str], shape: tuple[int, int, int]
                  ) -> torch.Tensor:
    """``[K, h, w]`` True where the pixel's panoptic category is *not* one of ``names`` (case-insensitive).
    ``segs``: one :class:`~pvslam_core.types.PanopticSegmentation` (or None) per keyframe at the depth resolution."""
    k, h, w = shape
    out = torch.ones(shape, dtype=torch.bool)
    wanted = {n.lower() for n in names}
    drop_ids = []
    for c in (categories.values() if isinstance(categories, dict) else categories or ()):
        name = c["name"] if isinstance(c, dict) else c.name
        if str(name).lower() in wanted:
            drop_ids.append(int(c["id"] if isinstance(c, dict) else c.id))
    if not drop_ids:
        return out
    drop = torch.tensor(drop_ids, dtype=torch.int64)
    for i, seg in enumerate(segs):  # one small lookup per keyframe; the per-pixel work is vectorised
        if seg is None:
            continue
        cat = seg.category_map()[:h, :w]
        out[i, : cat.shape[0], : cat.shape[1]] &= ~torch.isin(cat, drop)
    return out


def clean_mask(poses_wc: Any, disps: Any, intr: Any, cfg: CloudFilter, segs: Optional[Sequence[Any]] = None,
               categories: Any = None) -> torch.Tensor:
    """``bool [K, h, w]``: the keyframe pixels that go into the point cloud under ``cfg``."""
    d = torch.as_tensor(np.asarray(disps) if not torch.is_tensor(disps) else disps).double()
    if d.ndim == 2:
        d = d[None]
    poses = torch.as_tensor(np.asarray(poses_wc) if not torch.is_tensor(poses_wc) else poses_wc).double()
    poses = poses.reshape(-1, 7)
    k4 = torch.as_tensor(np.asarray(intr) if not torch.is_tensor(intr) else intr).double().reshape(-1)[:4]
    keep = _valid(d)
    if cfg.depth_factor:
        keep &= far_mask(d, cfg.depth_factor)
    if cfg.edge_ratio:
        keep &= edge_mask(d, cfg.edge_ratio)
    if cfg.min_views > 0:
        keep &= consistency_count(poses, d, k4, cfg.neighbours, cfg.consistency) >= cfg.min_views
    if segs is not None and categories and cfg.drop_categories:
        keep &= category_mask(segs, categories, cfg.drop_categories, tuple(d.shape))
    return keep


def voxel_downsample(points: np.ndarray, voxel: float, colors: Optional[np.ndarray] = None,
                     extra: Optional[dict[str, np.ndarray]] = None, average: bool = True
                     ) -> tuple[np.ndarray, Optional[np.ndarray], dict[str, np.ndarray]]:
    """One point per occupied voxel of edge ``voxel``: the mean position and colour (``average``) or the first
    point's (``average=False``, e.g. to keep panoptic colours unmixed). ``extra`` columns take the first point's
    value. Returns ``points [M, 3]``, ``colors [M, 3]`` (or None), ``extra``."""
    extra = dict(extra or {})
    if voxel <= 0 or len(points) == 0:
        return points, colors, extra
    keys = np.floor(points / voxel).astype(np.int64)
    _, first, inv = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    m = len(first)
    if average:
        cnt = np.bincount(inv, minlength=m).astype(np.float64)[:, None]
        pts = np.stack([np.bincount(inv, weights=points[:, c], minlength=m) for c in range(3)], 1) / cnt
        cols = None
        if colors is not None:
            cols = np.stack([np.bincount(inv, weights=colors[:, c].astype(np.float64), minlength=m)
                             for c in range(3)], 1) / cnt
            cols = np.clip(np.round(cols), 0, 255).astype(np.uint8)
        pts = pts.astype(points.dtype)
    else:
        pts, cols = points[first], (colors[first] if colors is not None else None)
    return pts, cols, {k: v[first] for k, v in extra.items()}


def write_clouds(run_dir: Any, poses_wc: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor,
                 images: torch.Tensor, segs: Sequence[Any], categories: Any, frame_index: Any, outputs: Any
                 ) -> dict[str, int]:
    """``cloud_rgb.ply`` (and ``cloud_panoptic.ply`` when every keyframe has a segmentation and categories are
    known) from keyframe depth, cleaned by :func:`clean_mask` with the ``[outputs]`` section's ``ply_*`` settings
    and optionally voxel-downsampled. Each point carries ``frame_index`` (int32, its keyframe's input-frame index)
    so exporters know which image observes it. Returns point counts ``{"valid", "kept", "rgb", "panoptic"}``."""
    from pathlib import Path

    from .ply import _backproject, _resize_to, panoptic_point_cloud_from_keyframes, write_ply

    run_dir = Path(run_dir)
    cfg = CloudFilter.from_outputs(outputs)
    have_segs = bool(categories) and len(segs) == len(disps) and all(s is not None for s in segs)
    mask = clean_mask(poses_wc, disps, intr, cfg, segs if have_segs else None, categories)
    fi = np.asarray(frame_index, dtype=np.int64).reshape(-1)
    xw, valid, (h, w) = _backproject(poses_wc, disps, intr, None, None, 1, mask)
    v = valid.numpy()
    pts = xw.numpy()[v].astype(np.float32)
    imgs = _resize_to(np.asarray(images), h, w, nearest=False)
    cols = np.ascontiguousarray(imgs.transpose(0, 2, 3, 1))[v].astype(np.uint8)
    extra = {"frame_index": fi[np.nonzero(v)[0]].astype(np.int32)}
    voxel = float(outputs.ply_voxel) * float(torch.nanmedian(median_depth(torch.as_tensor(disps).double())))
    if voxel > 0 and np.isfinite(voxel):
        pts, cols, extra = voxel_downsample(pts, voxel, cols, extra, average=True)
    stats = {"valid": int(_valid(torch.as_tensor(disps)).sum()), "kept": int(v.sum()), "rgb": len(pts), "panoptic": 0}
    write_ply(run_dir / "cloud_rgb.ply", pts, cols, extra=extra)
    if have_segs:
        pts2, cols2, extra2 = panoptic_point_cloud_from_keyframes(poses_wc, disps, intr, segs, categories,
                                                                  max_depth=None, rel_max_depth=None, mask=mask)
        extra2["frame_index"] = fi[extra2.pop("keyframe")].astype(np.int32)
        if voxel > 0 and np.isfinite(voxel):  # keep one real point per voxel: averaging would mix classes
            pts2, cols2, extra2 = voxel_downsample(pts2, voxel, cols2, extra2, average=False)
        write_ply(run_dir / "cloud_panoptic.ply", pts2, cols2, extra=extra2)
        stats["panoptic"] = len(pts2)
    return stats


def write_run_clouds(run) -> dict[str, int]:
    """The run's clouds from its final map (``run``: :class:`.formats.MapOutput`; a line of ``MAP_WRITERS``)."""
    kf = run.keyframes
    ids = kf.ids.tolist()
    images = torch.stack([kf.images[i] for i in ids])
    segs = [kf.segs.get(i) for i in ids]
    stats = write_clouds(run.dir, kf.poses, kf.disps, kf.intrinsics, images, segs, run.categories, kf.frame_index,
                         run.outputs)
    LOG.info("point cloud: %d of %d keyframe depth pixels kept (relative depth, edges, multi-view consistency, "
             "categories), %d points written", stats["kept"], stats["valid"], stats["rgb"])
    return stats
