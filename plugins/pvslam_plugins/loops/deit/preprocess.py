"""Image preprocessing for the DeiT descriptor: uint8 RGB frames -> normalised ``[B, 3, h, w]`` model input.

Two modes:

* ``center_crop``: DeiT's eval transform (deit/datasets.py ``build_transform``): resize the shorter side to
  ``int(S / crop_pct)`` (256 for S = 224, crop_pct 0.875; the longer side ``int(S/crop_pct * long / short)`` as
  torchvision computes it), bicubic, then centre-crop ``S x S``.  This is what the ImageNet numbers of the
  official weights were measured with, but on a wide driving frame (KITTI is 3.3:1) it throws away most of
  the image, including the sides where most of the revisited structure is.
* ``full_frame`` (default of the detector): the whole frame, resized.  With ``input_size = (h, w)`` exactly that
  (multiples of the patch size; aspect ratio not kept).  With an int ``S`` the frame keeps its aspect ratio on a
  token budget of about ``(S / patch)^2`` patches (the cost of an ``S x S`` input): grid ``gh x gw`` with
  ``gh = round(sqrt(budget * H / W))``, ``gw = round(budget / gh)``; KITTI at S = 224 gives 8 x 24 patches
  (128 x 384 pixels).  Position embeddings are resampled to that grid by the model.

Resizing is ``F.interpolate(mode="bicubic", antialias=True)`` on float images, i.e. PIL's bicubic filter (a = -0.5,
support widened when shrinking), which the DeiT transform calls through torchvision; PIL rounds its output to
uint8 after each of its two separable passes, this does not (measured: <= 1.5/255, mean 0.3/255, before
normalisation).  Values are clamped to [0, 1] as PIL's uint8
output is.  Then ``(x - mean) / std`` with the ImageNet constants.
"""
from __future__ import annotations

import math
from typing import Sequence, Union

import torch
import torch.nn.functional as F

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

Images = Union[torch.Tensor, Sequence[torch.Tensor]]
SizeLike = Union[int, tuple[int, int], list]


def full_frame_size(height: int, width: int, input_size: SizeLike, patch_size: int = 16) -> tuple[int, int]:
    """Model input ``(h, w)`` for a ``height x width`` frame in ``full_frame`` mode (see module docstring)."""
    if not isinstance(input_size, int):
        h, w = int(input_size[0]), int(input_size[1])
        if h % patch_size or w % patch_size or h <= 0 or w <= 0:
            raise ValueError(f"input_size {(h, w)} must be positive multiples of the patch size {patch_size}")
        return h, w
    budget = max(1, round((input_size / patch_size) ** 2))
    gh = max(1, round(math.sqrt(budget * height / width)))
    gw = max(1, round(budget / gh))
    return gh * patch_size, gw * patch_size


def center_crop_resize_size(height: int, width: int, size: int, crop_pct: float = 0.875) -> tuple[int, int]:
    """``(h, w)`` after DeiT's ``Resize(int(size / crop_pct))`` (shorter side; torchvision's rounding)."""
    short_target = int(size / crop_pct)
    if height <= width:
        return short_target, int(short_target * width / height)
    return int(short_target * height / width), short_target


def _to_float_batch(images: torch.Tensor) -> torch.Tensor:
    if images.dim() == 3:
        images = images[None]
    if images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"expected RGB images [3, H, W] or [B, 3, H, W], got {tuple(images.shape)}")
    if images.dtype == torch.uint8:
        return images.float() / 255.0
    if not images.is_floating_point():
        raise ValueError(f"images must be uint8 (0..255) or float (0..1), got {images.dtype}")
    return images.float()


def _resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bicubic", antialias=True, align_corners=False).clamp_(0.0, 1.0)


def preprocess(
    images: Images,
    input_size: SizeLike = 224,
    mode: str = "full_frame",
    crop_pct: float = 0.875,
    patch_size: int = 16,
    mean: Sequence[float] = IMAGENET_MEAN,
    std: Sequence[float] = IMAGENET_STD,
) -> torch.Tensor:
    """RGB ``uint8 [B,3,H,W]`` / ``[3,H,W]`` (or float in [0, 1], or a list of such with equal sizes after
    preprocessing) -> normalised float32 ``[B, 3, h, w]``."""
    if not isinstance(images, torch.Tensor):
        outs = [preprocess(im, input_size, mode, crop_pct, patch_size, mean, std) for im in images]
        sizes = {tuple(o.shape[-2:]) for o in outs}
        if len(sizes) > 1:
            raise ValueError(f"images of different shapes give different input sizes {sorted(sizes)}; pass an "
                             "explicit input_size (h, w) or use mode='center_crop'")
        return torch.cat(outs)
    x = _to_float_batch(images)
    H, W = x.shape[-2:]
    if mode == "center_crop":
        if not isinstance(input_size, int):
            if int(input_size[0]) != int(input_size[1]):
                raise ValueError(f"center_crop needs a square input_size, got {tuple(input_size)}")
            input_size = int(input_size[0])
        if input_size % patch_size:
            raise ValueError(f"input_size {input_size} is not a multiple of the patch size {patch_size}")
        rh, rw = center_crop_resize_size(H, W, input_size, crop_pct)
        x = _resize(x, (rh, rw))
        top = int(round((rh - input_size) / 2.0))  # torchvision CenterCrop
        left = int(round((rw - input_size) / 2.0))
        x = x[..., top : top + input_size, left : left + input_size]
    elif mode == "full_frame":
        x = _resize(x, full_frame_size(H, W, input_size, patch_size))
    else:
        raise ValueError(f"unknown preprocessing mode {mode!r} (center_crop | full_frame)")
    m = torch.tensor(mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    s = torch.tensor(std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return ((x - m) / s).contiguous()
