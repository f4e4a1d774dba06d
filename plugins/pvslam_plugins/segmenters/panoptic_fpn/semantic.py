"""Semantic FPN head (detectron2 SemSegFPNHead): one branch per level brought to stride 4, summed, 1x1 predictor.

Branch of level ``p_k`` (stride ``2^k``): ``max(1, k - 2)`` blocks of [3x3 conv (no bias) + GroupNorm + ReLU],
each followed by a x2 bilinear upsampling while the stride is still above 4.  State-dict names
``p{k}.{2i}`` (conv) / ``p{k}.{2i}.norm`` and ``predictor`` (the module is ``sem_seg_head`` in the full model).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .config import SemSegConfig
from .layers import Conv2d, c2_msra_fill, get_norm, init_normal

__all__ = ["SemSegFPNHead"]


class SemSegFPNHead(nn.Module):
    def __init__(self, cfg: SemSegConfig, in_channels: int, strides: dict[str, int]) -> None:
        super().__init__()
        self.cfg = cfg
        self.in_features = [k for k in ("p2", "p3", "p4", "p5") if k in strides]
        for name in self.in_features:
            stride = strides[name]
            length = max(1, int(round(math.log2(stride) - math.log2(cfg.common_stride))))
            ops: list[nn.Module] = []
            for k in range(length):
                conv = Conv2d(in_channels if k == 0 else cfg.conv_dims, cfg.conv_dims, 3, padding=1,
                              bias=not cfg.norm, norm=get_norm(cfg.norm, cfg.conv_dims, cfg.gn_groups),
                              activation=F.relu)
                c2_msra_fill(conv)
                ops.append(conv)
                if stride != cfg.common_stride:
                    ops.append(nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False))
            self.add_module(name, nn.Sequential(*ops))
        self.predictor = nn.Conv2d(cfg.conv_dims, cfg.num_classes, 1)
        init_normal(self.predictor, 0.01)

    def forward(self, features: dict[str, torch.Tensor] | list[torch.Tensor]) -> torch.Tensor:
        """p2..p5 ``[B, C, H/s, W/s]`` -> logits ``[B, num_classes, H, W]`` at the (padded) input resolution."""
        if isinstance(features, dict):
            features = [features[n] for n in self.in_features]
        x = None
        for name, f in zip(self.in_features, features):
            y = getattr(self, name)(f)
            x = y if x is None else x + y
        x = self.predictor(x)
        return F.interpolate(x, scale_factor=self.cfg.common_stride, mode="bilinear", align_corners=False)
