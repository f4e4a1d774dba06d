"""Image helpers shared by plugins: RGB -> grayscale and OpenCV's DIS optical flow.

Images follow :mod:`pvslam_core.types`: ``uint8 [3, H, W]`` RGB tensors (numpy ``[H, W, 3]`` / ``[H, W]`` arrays are
accepted too).
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np
import torch

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def create_dis(preset: str = "fast", finest_scale: Optional[int] = None):
    """An OpenCV DIS optical-flow object for ``preset``; ``finest_scale`` None keeps the preset's finest level."""
    if preset not in DIS_PRESETS:
        raise ValueError(f"unknown DIS preset {preset!r}; choose one of {sorted(DIS_PRESETS)}")
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
    if finest_scale is not None:
        dis.setFinestScale(int(finest_scale))
    return dis


def to_gray(image, scale: float = 1.0) -> np.ndarray:
    """Contiguous ``uint8 [H', W']`` luminance of an RGB ``uint8 [3, H, W]`` tensor (or ``[H, W]`` / ``[H, W, 3]``
    array; other dtypes are rounded and clipped to 0-255), resized by ``scale`` (area interpolation).

    A planar tensor is merged with ``cv2.merge`` (~0.1 ms at 320x240; a torch/numpy transpose copy costs ~1 ms).
    """
    if isinstance(image, torch.Tensor):
        t = image.detach()
        if t.device.type != "cpu":
            t = t.cpu()
        if t.dtype != torch.uint8:
            t = t.float().clamp(0, 255).round().to(torch.uint8)
        a = t.contiguous().numpy()
        if a.ndim == 3 and a.shape[0] == 3:
            gray = cv2.cvtColor(cv2.merge([a[0], a[1], a[2]]), cv2.COLOR_RGB2GRAY)
        elif a.ndim == 3 and a.shape[0] == 1:
            gray = a[0]
        else:
            gray = a if a.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(a[..., :3]), cv2.COLOR_RGB2GRAY)
    else:
        arr = np.asarray(image)
        if arr.dtype != np.uint8:
            arr = np.clip(arr, 0, 255).astype(np.uint8)
        if arr.ndim == 3:
            gray = cv2.cvtColor(np.ascontiguousarray(arr[..., :3]), cv2.COLOR_RGB2GRAY) if arr.shape[2] >= 3 \
                else arr[..., 0]
        else:
            gray = arr
    if gray.ndim != 2:
        raise ValueError(f"expected an image [3, H, W] (torch) or [H, W(, 3)] (numpy), got shape {tuple(gray.shape)}")
    if scale != 1.0:
        h, w = gray.shape
        gray = cv2.resize(gray, (max(1, int(round(w * scale))), max(1, int(round(h * scale)))),
                          interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(gray)
