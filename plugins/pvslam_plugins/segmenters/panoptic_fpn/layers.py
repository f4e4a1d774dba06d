"""Small layers with detectron2's parameter names: a conv that owns its norm (``<conv>.norm.*``), frozen BN.

detectron2 stores a conv's normalisation as a child called ``norm`` (``backbone.bottom_up.res2.0.conv1.norm.
running_mean``); :class:`Conv2d` reproduces that layout so checkpoints load by name without renaming.
"""
from __future__ import annotations

from typing import Callable, Optional

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["FrozenBatchNorm2d", "Conv2d", "get_norm", "c2_msra_fill", "c2_xavier_fill", "init_normal", "NORMS"]

NORMS = ("FrozenBN", "BN", "GN", "")


class FrozenBatchNorm2d(nn.Module):
    """BatchNorm with fixed statistics and affine parameters: ``(x - mean) / sqrt(var + eps) * weight + bias``.

    All four tensors are buffers (detectron2 layers/batch_norm.py), so they appear in the state_dict but are not
    trained; eps = 1e-5.  Initialised to the identity (mean 0, var 1, weight 1, bias 0).
    """

    def __init__(self, num_features: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.num_features = num_features
        self.eps = eps
        self.register_buffer("weight", torch.ones(num_features))
        self.register_buffer("bias", torch.zeros(num_features))
        self.register_buffer("running_mean", torch.zeros(num_features))
        # 1 - eps (as detectron2): a fresh layer is exactly the identity
        self.register_buffer("running_var", torch.ones(num_features) - eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # folded into one per-channel affine map (cheaper than F.batch_norm on the CPU, same values)
        scale = self.weight * (self.running_var + self.eps).rsqrt()
        shift = self.bias - self.running_mean * scale
        return x * scale.view(1, -1, 1, 1).to(x.dtype) + shift.view(1, -1, 1, 1).to(x.dtype)

    def extra_repr(self) -> str:
        return f"{self.num_features}, eps={self.eps}"


def get_norm(norm: str, channels: int, gn_groups: int = 32) -> Optional[nn.Module]:
    """detectron2's get_norm for the names used here: "FrozenBN", "BN", "GN" (``gn_groups`` groups) or ""."""
    if norm == "":
        return None
    if norm == "FrozenBN":
        return FrozenBatchNorm2d(channels)
    if norm == "BN":
        return nn.BatchNorm2d(channels)
    if norm == "GN":
        if channels % gn_groups:
            raise ValueError(f"GroupNorm: {channels} channels are not divisible into {gn_groups} groups")
        return nn.GroupNorm(gn_groups, channels)
    raise ValueError(f"unknown norm {norm!r}; expected one of {NORMS}")


class Conv2d(nn.Conv2d):
    """``nn.Conv2d`` followed by an optional ``norm`` child and activation (detectron2 layers/wrappers.py)."""

    def __init__(
        self, *args, norm: Optional[nn.Module] = None, activation: Optional[Callable] = None, **kwargs
    ) -> None:
        super().__init__(*args, **kwargs)
        self.norm = norm
        self.activation = activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.conv2d(x, self.weight, self.bias, self.stride, self.padding, self.dilation, self.groups)
        if self.norm is not None:
            x = self.norm(x)
        if self.activation is not None:
            x = self.activation(x)
        return x


def c2_msra_fill(module: nn.Module) -> None:
    """Caffe2 "MSRAFill" (detectron2 weight_init): kaiming normal, fan_out, ReLU gain; bias 0."""
    nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
    if getattr(module, "bias", None) is not None:
        nn.init.constant_(module.bias, 0)


def c2_xavier_fill(module: nn.Module) -> None:
    """Caffe2 "XavierFill" (detectron2 weight_init): kaiming uniform with a = 1; bias 0."""
    nn.init.kaiming_uniform_(module.weight, a=1)
    if getattr(module, "bias", None) is not None:
        nn.init.constant_(module.bias, 0)


def init_normal(module: nn.Module, std: float) -> None:
    nn.init.normal_(module.weight, std=std)
    if getattr(module, "bias", None) is not None:
        nn.init.constant_(module.bias, 0)

