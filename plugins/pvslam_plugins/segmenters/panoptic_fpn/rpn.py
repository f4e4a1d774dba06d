"""Region proposal network: anchors, the shared conv head, and test-time proposal selection (detectron2 RPN).

Anchors (reference/checkpoints.md §2.6): one size per level, ratios h/w in ``aspect_ratios``; cell anchor
``[-w/2, -h/2, w/2, h/2]`` with ``w = sqrt(size^2 / ratio)``, ``h = ratio * w``, ordered size-major then ratio;
centres at ``((x + offset) * stride, (y + offset) * stride)``; flattened per level in ``(H, W, A)`` order.
State-dict names: ``rpn_head.{conv, objectness_logits, anchor_deltas}`` (the RPN is ``proposal_generator``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from .config import RPNConfig
from .layers import init_normal
from .ops import apply_deltas, batched_nms, clip_boxes, nonempty

__all__ = ["cell_anchors", "grid_anchors", "RPNHead", "RPN", "Proposals"]


def cell_anchors(sizes: Sequence[float], aspect_ratios: Sequence[float]) -> torch.Tensor:
    """``[len(sizes) * len(ratios), 4]`` anchors centred on (0, 0), size-major (detectron2 generate_cell_anchors)."""
    anchors = []
    for size in sizes:
        area = size ** 2.0
        for ratio in aspect_ratios:
            w = math.sqrt(area / ratio)
            h = ratio * w
            anchors.append([-w / 2.0, -h / 2.0, w / 2.0, h / 2.0])
    return torch.tensor(anchors, dtype=torch.float32)


def grid_anchors(cell: torch.Tensor, grid_size: tuple[int, int], stride: int, offset: float = 0.0) -> torch.Tensor:
    """All anchors of one level: ``[H * W * A, 4]`` in (H, W, A) order for a feature map of ``grid_size (H, W)``."""
    h, w = grid_size
    dev = cell.device
    shifts_x = torch.arange(offset * stride, w * stride, step=stride, dtype=torch.float32, device=dev)
    shifts_y = torch.arange(offset * stride, h * stride, step=stride, dtype=torch.float32, device=dev)
    sy, sx = torch.meshgrid(shifts_y, shifts_x, indexing="ij")
    sx, sy = sx.reshape(-1), sy.reshape(-1)
    shifts = torch.stack((sx, sy, sx, sy), dim=1)
    return (shifts.view(-1, 1, 4) + cell.view(1, -1, 4)).reshape(-1, 4)


class RPNHead(nn.Module):
    """3x3 conv + ReLU shared across levels, then 1x1 objectness (A) and 1x1 box deltas (4A)."""

    def __init__(self, in_channels: int, num_anchors: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_channels, in_channels, 3, padding=1)
        self.objectness_logits = nn.Conv2d(in_channels, num_anchors, 1)
        self.anchor_deltas = nn.Conv2d(in_channels, num_anchors * 4, 1)
        for layer in (self.conv, self.objectness_logits, self.anchor_deltas):
            init_normal(layer, 0.01)

    def forward(self, features: list[torch.Tensor]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Per level: objectness ``[B, A, H, W]`` and deltas ``[B, 4A, H, W]``."""
        logits, deltas = [], []
        for x in features:
            t = F.relu(self.conv(x))
            logits.append(self.objectness_logits(t))
            deltas.append(self.anchor_deltas(t))
        return logits, deltas


@dataclass
class Proposals:
    """Proposals of one image, in network-input pixels."""

    boxes: torch.Tensor  # float [P, 4]
    logits: torch.Tensor  # float [P] objectness logits


class RPN(nn.Module):
    def __init__(self, cfg: RPNConfig, in_channels: int, strides: Sequence[int]) -> None:
        super().__init__()
        self.cfg = cfg
        self.strides = list(strides)
        self.num_anchors = len(cfg.aspect_ratios)
        self.rpn_head = RPNHead(in_channels, self.num_anchors)
        # not buffers: detectron2's HEAD keeps them out of the state_dict (old files carrying them are tolerated)
        self._cells = [cell_anchors([s], cfg.aspect_ratios) for s in cfg.anchor_sizes]

    def anchors(self, features: list[torch.Tensor]) -> list[torch.Tensor]:
        """Per level ``[H * W * A, 4]``."""
        return [grid_anchors(c.to(x.device), (int(x.shape[-2]), int(x.shape[-1])), s, self.cfg.anchor_offset)
                for c, x, s in zip(self._cells, features, self.strides)]

    def head_outputs(self, features: list[torch.Tensor]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Flattened per level: logits ``[B, H*W*A]`` and deltas ``[B, H*W*A, 4]`` in anchor order."""
        logits, deltas = self.rpn_head(features)
        flat_logits = [x.permute(0, 2, 3, 1).flatten(1) for x in logits]
        flat_deltas = []
        for d in deltas:
            b, _, h, w = d.shape
            flat_deltas.append(d.view(b, self.num_anchors, 4, h, w).permute(0, 3, 4, 1, 2).flatten(1, -2))
        return flat_logits, flat_deltas

    def forward(self, features: list[torch.Tensor], image_sizes: list[tuple[int, int]]) -> list[Proposals]:
        """Test-time proposals per image (p2..p6 features ``[B, C, h, w]``)."""
        logits, deltas = self.head_outputs(features)
        return self.select(self.anchors(features), logits, deltas, image_sizes, training=self.training)

    @torch.no_grad()
    def select(self, anchors: list[torch.Tensor], logits: list[torch.Tensor], deltas: list[torch.Tensor],
               image_sizes: list[tuple[int, int]], training: bool = False) -> list[Proposals]:
        """detectron2 find_top_rpn_proposals: per level top-k by logit, decode, clip, drop empty, NMS per level,
        keep the best ``post_nms_topk`` per image."""
        cfg = self.cfg
        pre_k = cfg.pre_nms_topk_train if training else cfg.pre_nms_topk_test
        post_k = cfg.post_nms_topk_train if training else cfg.post_nms_topk_test
        out = []
        for n, size in enumerate(image_sizes):
            boxes_l, scores_l, level_l = [], [], []
            for lvl, (a, lg, dl) in enumerate(zip(anchors, logits, deltas)):
                k = min(pre_k, lg.shape[1])
                top, idx = lg[n].topk(k)
                # decoding only the kept anchors gives the same boxes as decoding all then selecting
                boxes_l.append(apply_deltas(dl[n, idx], a[idx], cfg.bbox_reg_weights))
                scores_l.append(top)
                level_l.append(torch.full((k,), lvl, dtype=torch.int64, device=lg.device))
            boxes, scores, levels = torch.cat(boxes_l), torch.cat(scores_l), torch.cat(level_l)
            valid = torch.isfinite(boxes).all(dim=1) & torch.isfinite(scores)
            if not bool(valid.all()):
                boxes, scores, levels = boxes[valid], scores[valid], levels[valid]
            boxes = clip_boxes(boxes, size)
            keep = nonempty(boxes, cfg.min_size)
            boxes, scores, levels = boxes[keep], scores[keep], levels[keep]
            keep = batched_nms(boxes, scores, levels, cfg.nms_thresh)[:post_k]
            out.append(Proposals(boxes[keep], scores[keep]))
        return out
