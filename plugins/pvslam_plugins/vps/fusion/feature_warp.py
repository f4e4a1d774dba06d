"""Forward warping of a frame's FPN features into the next frame, per level (PVO's VO-enhanced VPS, anchors §2.2).

The motion comes from the VO at its own resolution ``(hf, wf)`` (usually 1/8 of the frame): a flow field on the
*previous* frame's grid, optionally replaced on static pixels by the rigid flow of depth + the two camera poses.
For each pyramid level the flow is sampled at the centre of every feature cell and converted to cells; each
previous cell is then scattered to the rounded target cell.  Several sources on one cell: the nearest one (lowest
z-depth) wins when depth is used, else the last in raster order (PVO).  Cells nothing lands on stay zero.

Cell geometry (see ``panoptic_fpn.features``): cell ``(i, j)`` of a level with stride ``s`` covers network-input
pixels ``[j s, (j + 1) s)``; one input pixel is ``W / w_in`` frame pixels.  Unlike PVO, the flow vectors are
scaled to the level (PVO resizes the field but keeps full-resolution vectors, and casts them to uint16, which
drops every leftward or upward motion: see reference/checkpoints.md §3).
"""
from __future__ import annotations

from typing import Mapping, Optional

import torch
import torch.nn.functional as F

__all__ = ["sample_to_level", "forward_warp_features", "warp_pyramid"]


def sample_to_level(field: torch.Tensor, level_hw: tuple[int, int], cell_px: tuple[float, float],
                    frame_hw: tuple[int, int], mode: str = "bilinear") -> torch.Tensor:
    """Sample ``field [B, K, hf, wf]`` (covering the ``frame_hw`` frame) at the centres of the cells of a level of
    ``level_hw`` cells of ``cell_px = (px_x, px_y)`` frame pixels -> ``[B, K, hl, wl]`` (border-clamped; cells
    on the padding take the nearest frame value)."""
    hl, wl = level_hw
    H, W = frame_hw
    dev, dt = field.device, field.dtype
    # cell centre in frame pixels: (j + 0.5) * px - 0.5; normalised (align_corners=False): (x + 0.5) / W * 2 - 1
    nx = (torch.arange(wl, device=dev, dtype=dt) + 0.5) * cell_px[0] / W * 2 - 1
    ny = (torch.arange(hl, device=dev, dtype=dt) + 0.5) * cell_px[1] / H * 2 - 1
    grid = torch.stack(torch.meshgrid(ny, nx, indexing="ij")[::-1], dim=-1)  # [hl, wl, 2] (x, y)
    grid = grid[None].expand(field.shape[0], hl, wl, 2)
    return F.grid_sample(field, grid, mode=mode, padding_mode="border", align_corners=False)


def forward_warp_features(feat: torch.Tensor, flow: torch.Tensor, depth: Optional[torch.Tensor] = None
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Scatter ``feat [B, C, h, w]`` by ``flow [B, 2, h, w]`` (in cells, source -> offset into the target).

    ``depth [B, h, w]`` (> 0 where known): the source with the smallest depth wins a target cell, unknown depths
    lose to known ones; ties and ``depth=None``: the last source in raster order.  Returns the warped features and
    the bool ``[B, h, w]`` mask of cells that received one."""
    B, C, h, w = feat.shape
    n = h * w
    dev = feat.device
    ys, xs = torch.meshgrid(torch.arange(h, device=dev), torch.arange(w, device=dev), indexing="ij")
    tx = torch.round(xs[None] + flow[:, 0])
    ty = torch.round(ys[None] + flow[:, 1])
    ok = torch.isfinite(tx) & torch.isfinite(ty) & (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)  # [B, h, w]
    base = (torch.arange(B, device=dev) * n)[:, None]
    src = (base + torch.arange(n, device=dev)[None]).reshape(-1)  # [B*n] global source index
    tgt = (base + (ty.clamp(0, h - 1) * w + tx.clamp(0, w - 1)).long().reshape(B, n)).reshape(-1)
    ok = ok.reshape(-1)
    src, tgt = src[ok], tgt[ok]
    if depth is not None and src.numel():
        z = depth.reshape(-1)[src].float()
        z = torch.where(z > 0, z, torch.full_like(z, float("inf")))
        best = torch.full((B * n,), float("inf"), device=dev).scatter_reduce(0, tgt, z, reduce="amin")
        keep = z <= best[tgt]
        src, tgt = src[keep], tgt[keep]
    winner = torch.full((B * n,), -1, dtype=torch.long, device=dev).scatter_reduce(0, tgt, src, reduce="amax")
    hit = winner >= 0
    flat = feat.permute(1, 0, 2, 3).reshape(C, B * n)
    out = torch.zeros_like(flat)
    out[:, hit] = flat[:, winner[hit]]
    return out.reshape(C, B, h, w).permute(1, 0, 2, 3), hit.reshape(B, h, w)


def warp_pyramid(levels: Mapping[str, torch.Tensor], strides: Mapping[str, int], flow: torch.Tensor,
                 frame_hw: tuple[int, int], input_hw: tuple[int, int], depth: Optional[torch.Tensor] = None
                 ) -> dict[str, torch.Tensor]:
    """Warp every level ``[B, C, hl, wl]`` by ``flow [B, 2, hf, wf]`` given in *frame* pixels on a grid covering the
    ``frame_hw`` frame; ``input_hw`` is the network input size (before padding); ``depth [B, hf, wf]`` optional."""
    H, W = frame_hw
    sx, sy = W / input_hw[1], H / input_hw[0]  # frame pixels per input pixel
    out = {}
    for name, feat in levels.items():
        s = strides[name]
        cell = (s * sx, s * sy)
        hw = tuple(feat.shape[-2:])
        f = sample_to_level(flow, hw, cell, frame_hw, "bilinear")
        f = torch.stack([f[:, 0] / cell[0], f[:, 1] / cell[1]], dim=1)
        d = None
        if depth is not None:
            d = sample_to_level(depth[:, None].float(), hw, cell, frame_hw, "nearest")[:, 0]
        out[name] = forward_warp_features(feat, f, d)[0]
    return out
