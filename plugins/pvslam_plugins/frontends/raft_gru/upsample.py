"""Upsampling from the 1/8 resolution: convex upsampling (DROID ``cvx_upsample``) and PVO's bilinear one.

Convex upsampling.  ``mask (B, 576, h, w)`` is viewed as ``(B, 1, 9, 8, 8, h, w)`` and softmaxed over the 9
neighbours ``k = 3*ky + kx`` of a 3x3 zero-padded unfold; mask channel ``k*64 + a*8 + b`` weights output pixel
``(8y + a, 8x + b)``.  The result is **not** multiplied by 8: right for disparity (upstream's use); flow in 1/8
pixels must be scaled by the caller (``8 * upsample_flow(...)`` gives full-resolution pixels).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

UP = 8


def cvx_upsample(data: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``data (B, h, w, D)``, ``mask (B, 576, h, w)`` -> ``(B, 8h, 8w, D)`` (convex combination, no x8)."""
    b, h, w, d = data.shape
    if mask.shape != (b, 9 * UP * UP, h, w):
        raise ValueError(f"mask must be {(b, 9 * UP * UP, h, w)} for data {tuple(data.shape)}, got {tuple(mask.shape)}")
    mask = torch.softmax(mask.reshape(b, 1, 9, UP, UP, h, w), dim=2)
    nb = F.unfold(data.permute(0, 3, 1, 2), [3, 3], padding=1).view(b, d, 9, 1, 1, h, w)
    up = torch.sum(mask * nb, dim=2)  # (B, D, 8, 8, h, w)
    return up.permute(0, 4, 2, 5, 3, 1).reshape(b, UP * h, UP * w, d)


def upsample_disp(disp: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``disp (B, N, h, w)``, ``mask (B, N, 576, h, w)`` -> ``(B, N, 8h, 8w)`` (upstream ``upsample_disp``)."""
    b, n, h, w = disp.shape
    up = cvx_upsample(disp.reshape(b * n, h, w, 1), mask.reshape(b * n, -1, h, w))
    return up.view(b, n, UP * h, UP * w)


def upsample_flow(flow: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``flow (B, N, h, w, D)``, ``mask (B, N, 576, h, w)`` -> ``(B, N, 8h, 8w, D)``; values NOT scaled by 8
    (PVO ``upsample_dim_x``)."""
    b, n, h, w, d = flow.shape
    up = cvx_upsample(flow.reshape(b * n, h, w, d), mask.reshape(b * n, -1, h, w))
    return up.view(b, n, UP * h, UP * w, d)


def upsample_inter(x: torch.Tensor) -> torch.Tensor:
    """PVO ``upsample_inter``: ``(B, N, h, w, D)`` -> ``(B, N, 8h, 8w, D)``, bilinear, ``align_corners=True``.

    Used by PVO for the dynamic mask (and flow x 8).  With ``align_corners=True`` the sampling depends only on
    the sizes, so an explicit ``size=(8h, 8w)`` equals upstream's ``scale_factor=8, recompute_scale_factor=True``.
    """
    b, n, h, w, d = x.shape
    y = x.permute(0, 1, 4, 2, 3).reshape(b * n, d, h, w)
    y = F.interpolate(y, size=(UP * h, UP * w), mode="bilinear", align_corners=True)
    return y.permute(0, 2, 3, 1).reshape(b, n, UP * h, UP * w, d)
