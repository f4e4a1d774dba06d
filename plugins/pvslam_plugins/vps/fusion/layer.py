"""PVO's fusion layer: one 3x3 convolution ``fusion_conv1`` (2C -> C) on ``cat(current, warped previous)``, shared
by every FPN level (PVO: C = 256, ``fusion_conv1.weight [256, 512, 3, 3]`` and ``.bias [256]``; checkpoints.md §3).
Parameter names are PVO's, so its converted layer loads strictly."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Union

import torch
from torch import nn

__all__ = ["FeatureFusion", "fusion_state_dict", "load_fusion"]

KEYS = ("fusion_conv1.weight", "fusion_conv1.bias")


class FeatureFusion(nn.Module):
    def __init__(self, channels: int = 256) -> None:
        super().__init__()
        self.channels = channels
        self.fusion_conv1 = nn.Conv2d(2 * channels, channels, 3, padding=1)
        self.reset_identity()

    @torch.no_grad()
    def reset_identity(self) -> None:
        """fused = current features exactly: the decode starts as the segmenter's own, so training (and a run
        without trained weights) can only move away from a working model, never start from a broken one.  The
        previous-frame half starts at zero; its gradient is not zero (it multiplies the warped features)."""
        w = self.fusion_conv1.weight
        w.zero_()
        idx = torch.arange(self.channels)
        w[idx, idx, 1, 1] = 1.0
        self.fusion_conv1.bias.zero_()

    def forward(self, current: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
        """``current``, ``warped`` ``[B, C, h, w]`` -> ``[B, C, h, w]`` (PVO's channel order: current first)."""
        return self.fusion_conv1(torch.cat([current, warped], dim=1))


def fusion_state_dict(sd: Mapping[str, torch.Tensor], source: str = "state_dict") -> dict[str, torch.Tensor]:
    """The ``fusion_conv1.*`` tensors of a state dict: a fusion-only one, or a whole PVO/detectron2 checkpoint
    (optionally under ``model``/``state_dict``, keys optionally prefixed, e.g. ``module.``)."""
    for top in ("model", "state_dict"):
        if top in sd and isinstance(sd[top], Mapping):
            sd = sd[top]
    out = {}
    for key in KEYS:
        hits = [k for k in sd if k == key or k.endswith("." + key)]
        if len(hits) != 1:
            raise KeyError(f"{source}: expected exactly one key ending in {key!r}, found {hits or 'none'} "
                           f"(among {len(sd)} keys)")
        out[key] = torch.as_tensor(sd[hits[0]])
    return out


def load_fusion(layer: FeatureFusion, src: Union[str, Path, Mapping[str, torch.Tensor]]) -> FeatureFusion:
    """Load ``fusion_conv1`` strictly from a file or a state dict; shape mismatches name key, expected and got."""
    if isinstance(src, Mapping):
        source, sd = "state_dict", fusion_state_dict(src)
    else:
        from pvslam_core.weights import load_torch_file

        source = str(src)
        sd = load_torch_file(src, "vps fusion weights", error=ValueError)
        if not isinstance(sd, Mapping):
            raise ValueError(f"vps fusion weights: {source}: holds a {type(sd).__name__}, not a state dict")
        try:
            sd = fusion_state_dict(sd, source)
        except KeyError as exc:  # a file: say it in the one-line error form of the other load paths
            raise ValueError(f"vps fusion weights: {exc.args[0]}") from None
    own = layer.state_dict()
    for k, v in sd.items():
        if tuple(v.shape) != tuple(own[k].shape):
            raise ValueError(f"{source}: {k} has shape {tuple(v.shape)}, the fusion layer for {layer.channels}-channel "
                             f"features expects {tuple(own[k].shape)}")
    layer.load_state_dict(sd, strict=True)
    return layer
