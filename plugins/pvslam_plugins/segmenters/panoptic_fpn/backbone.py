"""ResNet (detectron2 layout) and FPN P2-P6 with the parameter names of detectron2's checkpoints.

State-dict layout (reference/checkpoints.md §2.3): ``bottom_up.stem.conv1``, ``bottom_up.res{2..5}.{i}.
{conv1,conv2,conv3,shortcut}`` (each conv bias-free with its norm at ``.norm``), ``fpn_lateral{2..5}``,
``fpn_output{2..5}``; the FPN module itself is ``backbone`` in the full model.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from .config import FPNConfig, ResNetConfig
from .layers import Conv2d, c2_msra_fill, c2_xavier_fill, get_norm

__all__ = ["ResNet", "BasicBlock", "BottleneckBlock", "BasicStem", "FPN", "STAGE_BLOCKS"]

#: blocks per stage res2..res5
STAGE_BLOCKS = {18: (2, 2, 2, 2), 34: (3, 4, 6, 3), 50: (3, 4, 6, 3), 101: (3, 4, 23, 3)}


class BasicStem(nn.Module):
    """conv1 7x7 stride 2 (+norm, ReLU), then max-pool 3x3 stride 2: stride 4 in total."""

    def __init__(self, in_channels: int, out_channels: int, norm: str, gn_groups: int) -> None:
        super().__init__()
        self.conv1 = Conv2d(in_channels, out_channels, 7, stride=2, padding=3, bias=False,
                            norm=get_norm(norm, out_channels, gn_groups))
        c2_msra_fill(self.conv1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu_(self.conv1(x))
        return F.max_pool2d(x, kernel_size=3, stride=2, padding=1)


class BottleneckBlock(nn.Module):
    """A 1x1, a 3x3 and a 1x1 convolution with a projection shortcut when the channel count changes.

    With ``stride_in_1x1`` (MSRA models) a stride-2 block downsamples in conv1, otherwise in the 3x3 conv2."""

    def __init__(self, in_channels: int, out_channels: int, bottleneck_channels: int, stride: int, norm: str,
                 gn_groups: int, stride_in_1x1: bool) -> None:
        super().__init__()
        self.shortcut: Optional[Conv2d] = None
        if in_channels != out_channels:
            self.shortcut = Conv2d(in_channels, out_channels, 1, stride=stride, bias=False,
                                   norm=get_norm(norm, out_channels, gn_groups))
        s1, s3 = (stride, 1) if stride_in_1x1 else (1, stride)
        self.conv1 = Conv2d(in_channels, bottleneck_channels, 1, stride=s1, bias=False,
                            norm=get_norm(norm, bottleneck_channels, gn_groups))
        self.conv2 = Conv2d(bottleneck_channels, bottleneck_channels, 3, stride=s3, padding=1, bias=False,
                            norm=get_norm(norm, bottleneck_channels, gn_groups))
        self.conv3 = Conv2d(bottleneck_channels, out_channels, 1, bias=False,
                            norm=get_norm(norm, out_channels, gn_groups))
        for layer in (self.conv1, self.conv2, self.conv3, self.shortcut):
            if layer is not None:
                c2_msra_fill(layer)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu_(self.conv1(x))
        out = F.relu_(self.conv2(out))
        out = self.conv3(out)
        out = out + (self.shortcut(x) if self.shortcut is not None else x)
        return F.relu_(out)


class BasicBlock(nn.Module):
    """Two 3x3 convs (ResNet-18/34), the first one carrying the stride; projection shortcut if needed."""

    def __init__(self, in_channels: int, out_channels: int, stride: int, norm: str, gn_groups: int) -> None:
        super().__init__()
        self.shortcut: Optional[Conv2d] = None
        if in_channels != out_channels:
            self.shortcut = Conv2d(in_channels, out_channels, 1, stride=stride, bias=False,
                                   norm=get_norm(norm, out_channels, gn_groups))
        self.conv1 = Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False,
                            norm=get_norm(norm, out_channels, gn_groups))
        self.conv2 = Conv2d(out_channels, out_channels, 3, padding=1, bias=False,
                            norm=get_norm(norm, out_channels, gn_groups))
        for layer in (self.conv1, self.conv2, self.shortcut):
            if layer is not None:
                c2_msra_fill(layer)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu_(self.conv1(x))
        out = self.conv2(out)
        out = out + (self.shortcut(x) if self.shortcut is not None else x)
        return F.relu_(out)


class ResNet(nn.Module):
    """Stem + stages res2..res5 (strides 4, 8, 16, 32); ``forward`` returns ``{"res2": .., ..., "res5": ..}``."""

    def __init__(self, cfg: ResNetConfig, in_channels: int = 3) -> None:
        super().__init__()
        self.stem = BasicStem(in_channels, cfg.stem_out_channels, cfg.norm, cfg.gn_groups)
        bottleneck = cfg.depth >= 50
        in_ch = cfg.stem_out_channels
        out_ch = cfg.res2_out_channels
        mid_ch = cfg.width_per_group
        self.stage_names = []
        self.out_channels: dict[str, int] = {}
        self.strides: dict[str, int] = {}
        for k, n_blocks in enumerate(STAGE_BLOCKS[cfg.depth]):
            name = f"res{k + 2}"
            blocks = []
            for i in range(n_blocks):
                stride = 2 if (i == 0 and k > 0) else 1
                if bottleneck:
                    blocks.append(BottleneckBlock(in_ch, out_ch, mid_ch, stride, cfg.norm, cfg.gn_groups,
                                                  cfg.stride_in_1x1))
                else:
                    blocks.append(BasicBlock(in_ch, out_ch, stride, cfg.norm, cfg.gn_groups))
                in_ch = out_ch
            self.add_module(name, nn.Sequential(*blocks))
            self.stage_names.append(name)
            self.out_channels[name] = out_ch
            self.strides[name] = 2 ** (k + 2)
            out_ch *= 2
            mid_ch *= 2

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        x = self.stem(x)
        out = {}
        for name in self.stage_names:
            x = getattr(self, name)(x)
            out[name] = x
        return out


class FPN(nn.Module):
    """Feature pyramid on res2..res5: lateral 1x1 convs, nearest x2 top-down sum, 3x3 output convs; p6 =
    max-pool(kernel 1, stride 2) of p5 (detectron2 LastLevelMaxPool).  Input sizes must be multiples of 32."""

    def __init__(self, bottom_up: ResNet, cfg: FPNConfig) -> None:
        super().__init__()
        self.out_channels = cfg.out_channels
        use_bias = cfg.norm == ""
        for k, stage in enumerate(bottom_up.stage_names):
            level = k + 2
            lateral = Conv2d(bottom_up.out_channels[stage], cfg.out_channels, 1, bias=use_bias,
                             norm=get_norm(cfg.norm, cfg.out_channels, cfg.gn_groups))
            output = Conv2d(cfg.out_channels, cfg.out_channels, 3, padding=1, bias=use_bias,
                            norm=get_norm(cfg.norm, cfg.out_channels, cfg.gn_groups))
            c2_xavier_fill(lateral)
            c2_xavier_fill(output)
            self.add_module(f"fpn_lateral{level}", lateral)
            self.add_module(f"fpn_output{level}", output)
        # registered after the lateral/output convs, as detectron2 does: the state_dict lists them first
        self.bottom_up = bottom_up
        self.level_names = [f"p{k}" for k in range(2, 7)]
        self.strides = {f"p{k}": 2 ** k for k in range(2, 7)}

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """``x [B, 3, H, W]`` (normalised, padded) -> ``{"p2": [B, C, H/4, W/4], ..., "p6": [B, C, H/64, W/64]}``."""
        bottom = self.bottom_up(x)
        prev = self.fpn_lateral5(bottom["res5"])
        outs = {"p5": self.fpn_output5(prev)}
        for level in (4, 3, 2):
            top_down = F.interpolate(prev, scale_factor=2.0, mode="nearest")
            prev = getattr(self, f"fpn_lateral{level}")(bottom[f"res{level}"]) + top_down
            outs[f"p{level}"] = getattr(self, f"fpn_output{level}")(prev)
        outs["p6"] = F.max_pool2d(outs["p5"], kernel_size=1, stride=2, padding=0)
        return {name: outs[name] for name in self.level_names}
