"""Training targets of PanopticFPN: detectron2's training-time rules (Matcher, subsampling, Box2BoxTransform
``get_deltas``, mask ``crop_and_resize``), as plain functions on one image's tensors.

* Matching (detectron2 Matcher): IoU ``[G, N]`` between ground-truth and predicted boxes; each prediction takes its
  best ground truth; label 1 if that IoU >= ``hi``, 0 if < ``lo``, -1 (ignored) in between.  With
  ``allow_low_quality`` every ground truth's best predictions (ties included) become positive as well, so an object
  smaller than every anchor still has a positive anchor (detectron2 does this for the RPN only).
* Sampling (detectron2 subsample_labels): at most ``num * positive_fraction`` random positives, negatives fill the
  rest of ``num``.
* Box regression targets: ``dx = wx (gx - px) / pw``, ``dw = ww log(gw / pw)`` (the inverse of
  :func:`~.ops.apply_deltas`).
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from .ops import box_iou, roi_align_fixed

__all__ = ["encode_deltas", "match", "subsample", "mask_targets"]


def encode_deltas(boxes: torch.Tensor, targets: torch.Tensor,
                  weights: Sequence[float] = (1.0, 1.0, 1.0, 1.0)) -> torch.Tensor:
    """``[N, 4]`` deltas that :func:`~.ops.apply_deltas` turns ``boxes`` into ``targets`` (both ``[N, 4]``)."""
    boxes, targets = boxes.float(), targets.float()
    pw, ph = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    px, py = boxes[:, 0] + 0.5 * pw, boxes[:, 1] + 0.5 * ph
    gw, gh = targets[:, 2] - targets[:, 0], targets[:, 3] - targets[:, 1]
    gx, gy = targets[:, 0] + 0.5 * gw, targets[:, 1] + 0.5 * gh
    wx, wy, ww, wh = weights
    return torch.stack((wx * (gx - px) / pw, wy * (gy - py) / ph, ww * torch.log(gw / pw),
                        wh * torch.log(gh / ph)), dim=1)


def match(gt_boxes: torch.Tensor, boxes: torch.Tensor, lo: float, hi: float,
          allow_low_quality: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Best ground truth of each of ``boxes [N, 4]`` among ``gt_boxes [G, 4]``.

    Returns ``(matched [N] int64 index into gt_boxes, labels [N] int8 in {-1, 0, 1})``; with no ground truth every
    box is background (label 0, matched 0)."""
    n = boxes.shape[0]
    if gt_boxes.shape[0] == 0:
        return (torch.zeros(n, dtype=torch.int64, device=boxes.device),
                torch.zeros(n, dtype=torch.int8, device=boxes.device))
    iou = box_iou(gt_boxes.float(), boxes.float())  # [G, N]
    vals, matched = iou.max(dim=0)
    labels = torch.full((n,), -1, dtype=torch.int8, device=boxes.device)
    labels[vals < lo] = 0
    labels[vals >= hi] = 1
    if allow_low_quality:
        best = iou.max(dim=1, keepdim=True).values  # [G, 1]
        # a ground truth no box overlaps at all gets no "best" box (detectron2 would mark every IoU-0 box)
        is_best = (iou == best) & (best > 0)
        labels[is_best.any(dim=0)] = 1
    return matched, labels


def subsample(labels: torch.Tensor, num: int, positive_fraction: float,
              generator: Optional[torch.Generator] = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Random positives (label 1, at most ``num * positive_fraction``) and negatives (label 0, the rest of ``num``):
    two int64 index tensors."""
    pos = torch.nonzero(labels == 1).squeeze(1)
    neg = torch.nonzero(labels == 0).squeeze(1)
    num_pos = min(int(num * positive_fraction), pos.numel())
    num_neg = min(num - num_pos, neg.numel())
    pos = pos[torch.randperm(pos.numel(), generator=generator, device="cpu")[:num_pos].to(pos.device)]
    neg = neg[torch.randperm(neg.numel(), generator=generator, device="cpu")[:num_neg].to(neg.device)]
    return pos, neg


def mask_targets(gt_masks: torch.Tensor, boxes: torch.Tensor, gt_index: torch.Tensor, size: int) -> torch.Tensor:
    """Binary ``[R, size, size]`` targets: ground-truth mask ``gt_index[r]`` (of ``gt_masks`` bool ``[G, H, W]``)
    cropped to ``boxes[r]`` and resized (ROIAlign, aligned, 2x2 samples per bin), then ``>= 0.5`` (detectron2
    BitMasks.crop_and_resize)."""
    if boxes.shape[0] == 0:
        return gt_masks.new_zeros((0, size, size), dtype=torch.float32)
    rois = torch.cat([gt_index.to(boxes.dtype)[:, None], boxes], dim=1)
    out = roi_align_fixed(gt_masks[:, None].float(), rois, size, 1.0, sampling_ratio=2, aligned=True)
    return (out[:, 0] >= 0.5).float()
