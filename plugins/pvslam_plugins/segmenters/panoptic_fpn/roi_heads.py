"""ROI heads at test time: multi-level ROIAlign pooling, the 2-FC box head with its predictor, and the mask head.

detectron2 StandardROIHeads (reference/checkpoints.md §2.7).  State-dict names: ``box_head.fc{1,2}``,
``box_predictor.{cls_score, bbox_pred}``, ``mask_head.{mask_fcn1..n, deconv, predictor}`` (the module is
``roi_heads`` in the full model).  Background is the *last* class logit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .config import BoxHeadConfig, MaskHeadConfig
from .layers import Conv2d, c2_msra_fill, c2_xavier_fill, init_normal
from .ops import apply_deltas, batched_nms, clip_boxes, roi_align, roi_align_fixed

__all__ = ["assign_levels", "ROIPooler", "Detections", "ROIHeads"]


def assign_levels(boxes: torch.Tensor, min_level: int, max_level: int, canonical_box_size: float = 224.0,
                  canonical_level: int = 4) -> torch.Tensor:
    """FPN level of each box (detectron2 assign_boxes_to_levels), returned as ``level - min_level``:
    ``clamp(floor(canonical_level + log2(sqrt(area) / canonical_box_size + 1e-8)), min_level, max_level)``."""
    size = torch.sqrt((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]))
    level = torch.floor(canonical_level + torch.log2(size / canonical_box_size + 1e-8))
    return (level.clamp(min=min_level, max=max_level) - min_level).to(torch.int64)


class ROIPooler(nn.Module):
    """ROIAlign (aligned = True, i.e. ROIAlignV2) of each box on the FPN level its size selects."""

    def __init__(self, output_size: int, strides: list[int], sampling_ratio: int, canonical_box_size: float,
                 canonical_level: int) -> None:
        super().__init__()
        self.output_size = output_size
        self.scales = [1.0 / s for s in strides]
        self.min_level = int(round(math.log2(strides[0])))
        self.max_level = int(round(math.log2(strides[-1])))
        self.sampling_ratio = sampling_ratio
        self.canonical_box_size = canonical_box_size
        self.canonical_level = canonical_level

    def _align(self, x: torch.Tensor, rois: torch.Tensor, scale: float) -> torch.Tensor:
        if self.sampling_ratio > 0:  # fixed sub-grid: the batched path (float32 positions)
            return roi_align_fixed(x, rois, self.output_size, scale, self.sampling_ratio, True)
        return roi_align(x, rois, self.output_size, scale, self.sampling_ratio, True)

    def forward(self, features: list[torch.Tensor], boxes: list[torch.Tensor]) -> torch.Tensor:
        """``features`` [B, C, h, w] per level, ``boxes`` one ``[R_i, 4]`` per image -> ``[sum R_i, C, S, S]``."""
        rois = torch.cat([torch.cat([torch.full_like(b[:, :1], i), b], dim=1) for i, b in enumerate(boxes)])
        c = features[0].shape[1]
        if rois.shape[0] == 0:
            return features[0].new_zeros((0, c, self.output_size, self.output_size))
        if len(features) == 1:
            return self._align(features[0], rois, self.scales[0])
        levels = assign_levels(rois[:, 1:], self.min_level, self.max_level, self.canonical_box_size,
                               self.canonical_level)
        out = features[0].new_zeros((rois.shape[0], c, self.output_size, self.output_size))
        for lvl, (x, scale) in enumerate(zip(features, self.scales)):
            idx = torch.nonzero(levels == lvl).squeeze(1)
            if idx.numel():
                out[idx] = self._align(x, rois[idx], scale)
        return out


@dataclass
class Detections:
    """Detections of one image. Boxes in network-input pixels until post-processing maps them to the frame."""

    boxes: torch.Tensor  # float [N, 4]
    scores: torch.Tensor  # float [N]
    classes: torch.Tensor  # int64 [N] contiguous thing class 0..K-1
    mask_probs: torch.Tensor | None = None  # float [N, M, M] sigmoid of the predicted class's mask logits
    masks: torch.Tensor | None = None  # bool [N, H, W] pasted into the output image

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    def take(self, keep: torch.Tensor) -> "Detections":
        return Detections(self.boxes[keep], self.scores[keep], self.classes[keep],
                          None if self.mask_probs is None else self.mask_probs[keep],
                          None if self.masks is None else self.masks[keep])


class FastRCNNConvFCHead(nn.Module):
    """Flatten (C, S, S) -> fc1 -> ReLU -> ... -> fcN -> ReLU."""

    def __init__(self, in_dim: int, fc_dim: int, num_fc: int) -> None:
        super().__init__()
        for k in range(num_fc):
            fc = nn.Linear(in_dim if k == 0 else fc_dim, fc_dim)
            c2_xavier_fill(fc)
            self.add_module(f"fc{k + 1}", fc)
        self.num_fc = num_fc

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.flatten(x, start_dim=1)
        for k in range(self.num_fc):
            x = F.relu(getattr(self, f"fc{k + 1}")(x))
        return x


class FastRCNNOutputLayers(nn.Module):
    def __init__(self, in_dim: int, num_classes: int) -> None:
        super().__init__()
        self.cls_score = nn.Linear(in_dim, num_classes + 1)
        self.bbox_pred = nn.Linear(in_dim, num_classes * 4)
        init_normal(self.cls_score, 0.01)
        init_normal(self.bbox_pred, 0.001)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.cls_score(x), self.bbox_pred(x)


class MaskRCNNConvUpsampleHead(nn.Module):
    """``num_conv`` 3x3 convs + ReLU, a 2x2 stride-2 transposed conv + ReLU, a 1x1 predictor (one mask per class)."""

    def __init__(self, in_channels: int, conv_dim: int, num_conv: int, num_masks: int) -> None:
        super().__init__()
        self.num_conv = num_conv
        for k in range(num_conv):
            conv = Conv2d(in_channels if k == 0 else conv_dim, conv_dim, 3, padding=1, activation=F.relu)
            c2_msra_fill(conv)
            self.add_module(f"mask_fcn{k + 1}", conv)
        self.deconv = nn.ConvTranspose2d(conv_dim if num_conv else in_channels, conv_dim, 2, stride=2)
        c2_msra_fill(self.deconv)
        self.predictor = nn.Conv2d(conv_dim, num_masks, 1)
        init_normal(self.predictor, 0.001)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for k in range(self.num_conv):
            x = getattr(self, f"mask_fcn{k + 1}")(x)
        return self.predictor(F.relu(self.deconv(x)))


class ROIHeads(nn.Module):
    """Box and mask branches on p2..p5 (the features must be given in that order)."""

    def __init__(self, box_cfg: BoxHeadConfig, mask_cfg: MaskHeadConfig, in_channels: int,
                 strides: list[int]) -> None:
        super().__init__()
        self.box_cfg, self.mask_cfg = box_cfg, mask_cfg
        self.num_classes = box_cfg.num_classes
        r = box_cfg.pooler_resolution
        self.box_pooler = ROIPooler(r, strides, box_cfg.sampling_ratio, box_cfg.canonical_box_size,
                                    box_cfg.canonical_level)
        self.mask_pooler = ROIPooler(mask_cfg.pooler_resolution, strides, mask_cfg.sampling_ratio,
                                     box_cfg.canonical_box_size, box_cfg.canonical_level)
        self.box_head = FastRCNNConvFCHead(in_channels * r * r, box_cfg.fc_dim, box_cfg.num_fc)
        self.box_predictor = FastRCNNOutputLayers(box_cfg.fc_dim, box_cfg.num_classes)
        self.mask_head = MaskRCNNConvUpsampleHead(in_channels, mask_cfg.conv_dim, mask_cfg.num_conv,
                                                  1 if mask_cfg.cls_agnostic else box_cfg.num_classes)

    # ------------------------------------------------------------------------------------------- raw outputs
    def box_outputs(self, features: list[torch.Tensor], boxes: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Class logits ``[R, K+1]`` and class-specific deltas ``[R, 4K]`` for all images' boxes, concatenated."""
        return self.box_predictor(self.box_head(self.box_pooler(features, boxes)))

    def mask_logits(self, features: list[torch.Tensor], boxes: list[torch.Tensor]) -> torch.Tensor:
        """``[R, K or 1, 2S, 2S]`` mask logits for the given boxes."""
        return self.mask_head(self.mask_pooler(features, boxes))

    # -------------------------------------------------------------------------------------------- inference
    @torch.no_grad()
    def detect(self, features: list[torch.Tensor], proposals: list[torch.Tensor],
               image_sizes: list[tuple[int, int]]) -> list[Detections]:
        """Boxes, scores and classes per image (detectron2 fast_rcnn_inference), then their masks."""
        logits, deltas = self.box_outputs(features, proposals)
        return self.predict_masks(features, self.inference(logits, deltas, proposals, image_sizes))

    def inference(self, logits: torch.Tensor, deltas: torch.Tensor, proposals: list[torch.Tensor],
                  image_sizes: list[tuple[int, int]]) -> list[Detections]:
        """detectron2 fast_rcnn_inference: the box predictor's outputs for all images' proposals (concatenated,
        as :meth:`box_outputs` gives them) -> per image softmax scores, class-specific decoded boxes, selection."""
        counts = [int(p.shape[0]) for p in proposals]
        dets = []
        for logit, delta, props, size in zip(logits.split(counts), deltas.split(counts), proposals, image_sizes):
            boxes = apply_deltas(delta, props, self.box_cfg.bbox_reg_weights)  # [R, 4K]
            dets.append(self.select_boxes(boxes, F.softmax(logit, dim=-1), size))
        return dets

    def select_boxes(self, boxes: torch.Tensor, scores: torch.Tensor, size: tuple[int, int]) -> Detections:
        """detectron2 fast_rcnn_inference_single_image: ``boxes [R, 4K]`` decoded per class, ``scores [R, K+1]``
        softmax -> clip, keep score > threshold, NMS per class, best ``detections_per_image``."""
        cfg = self.box_cfg
        valid = torch.isfinite(boxes).all(dim=1) & torch.isfinite(scores).all(dim=1)
        if not bool(valid.all()):
            boxes, scores = boxes[valid], scores[valid]
        scores = scores[:, :-1]  # drop background (last column)
        k = boxes.shape[1] // 4
        boxes = clip_boxes(boxes.reshape(-1, 4), size).view(-1, k, 4)
        mask = scores > cfg.score_thresh_test  # [R, K]
        inds = torch.nonzero(mask)  # (proposal, class), row-major as detectron2
        boxes = boxes[inds[:, 0], 0] if k == 1 else boxes[mask]
        scores = scores[mask]
        keep = batched_nms(boxes, scores, inds[:, 1], cfg.nms_thresh_test)[: cfg.detections_per_image]
        return Detections(boxes[keep], scores[keep], inds[keep, 1])

    def predict_masks(self, features: list[torch.Tensor], dets: list[Detections]) -> list[Detections]:
        """Sigmoid of each detection's class mask (``[N, 2S, 2S]``), from a re-pooling of the final boxes."""
        logits = self.mask_logits(features, [d.boxes for d in dets])
        if logits.shape[1] == 1:
            probs = logits[:, 0].sigmoid()
        else:
            classes = torch.cat([d.classes for d in dets])
            probs = logits[torch.arange(logits.shape[0], device=logits.device), classes].sigmoid()
        counts = [len(d) for d in dets]
        for d, p in zip(dets, probs.split(counts)):
            d.mask_probs = p
        return dets


def paste_masks(mask_probs: torch.Tensor, boxes: torch.Tensor, size: tuple[int, int],
                threshold: float = 0.5) -> torch.Tensor:
    """Paste ``[N, M, M]`` mask probabilities into an image of ``size (H, W)`` -> bool ``[N, H, W]``.

    detectron2 paste_masks_in_image: every pixel centre ``(x + 0.5, y + 0.5)`` is mapped into the box's
    ``[-1, 1]`` range and sampled with ``grid_sample(align_corners=False)`` (zeros outside), then ``>= threshold``.
    As detectron2 on the CPU, each mask is sampled only over its box grown by one pixel: outside the box every
    sample is below half the border value, i.e. below 0.5, so nothing is lost; the work is the boxes' area."""
    h, w = size
    n = int(mask_probs.shape[0])
    out = torch.zeros((n, h, w), dtype=torch.bool, device=mask_probs.device)
    b = boxes.float()
    lo = torch.clamp(b[:, :2].floor() - 1, min=0).to(torch.int64).tolist()
    hi = torch.minimum(b[:, 2:].ceil() + 1, torch.tensor([w, h], dtype=b.dtype, device=b.device))
    hi = hi.to(torch.int64).tolist()
    for i in range(n):  # one grid per mask: sizes differ, and the loop is over detections, not pixels
        (x0i, y0i), (x1i, y1i) = lo[i], hi[i]
        if x1i <= x0i or y1i <= y0i:
            continue
        x0, y0, x1, y1 = b[i]
        img_y = (torch.arange(y0i, y1i, device=b.device, dtype=torch.float32) + 0.5 - y0) / (y1 - y0) * 2 - 1
        img_x = (torch.arange(x0i, x1i, device=b.device, dtype=torch.float32) + 0.5 - x0) / (x1 - x0) * 2 - 1
        grid = torch.stack(torch.broadcast_tensors(img_x[None, :], img_y[:, None]), dim=-1)
        pasted = F.grid_sample(mask_probs[i][None, None].float(), grid[None], align_corners=False)
        out[i, y0i:y1i, x0i:x1i] = pasted[0, 0] >= threshold
    return out
