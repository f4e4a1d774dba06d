"""Image normalisation and DROID-SLAM's feature / context encoders (``BasicEncoder``), output stride 8.

Channel order.  The upstream networks were trained on **BGR** images (as ``cv2.imread`` returns them) and
``DroidNet.extract_features`` flips them to RGB before normalising with the ImageNet mean/std.  pvslam frames are
**RGB** (:mod:`pvslam_core.types`), so pvslam callers pass ``channel_order="rgb"`` (or use
:func:`frames_to_images`, which stacks RGB frames and is meant to be used with it); the flip is then skipped and
the network sees exactly the tensor upstream would have built from the BGR version of the same picture.

Layout of one encoder (parameter names equal upstream's, DIM = 32)::

    conv1 7x7 s2 (3 to 32 ch), norm1, ReLU
    layer1 = 2 x ResidualBlock(32, stride 1)
    layer2 = ResidualBlock(32 to 64 ch, stride 2, 1x1 stride-2 downsample) + ResidualBlock(64)
    layer3 = ResidualBlock(64 to 128 ch, stride 2) + ResidualBlock(128)
    conv2 1x1 (128 ch to output_dim)

``fnet`` uses ``InstanceNorm2d(affine=False)`` (no parameters, no running stats, so train and eval agree) and
``cnet`` no normalisation; neither has norm entries in the state_dict.
"""
from __future__ import annotations

from typing import Sequence, Union

import torch
import torch.nn as nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)  # RGB
IMAGENET_STD = (0.229, 0.224, 0.225)  # RGB
STRIDE = 8  # output stride of both encoders
DIM = 32  # width of the first stage

CHANNEL_ORDERS = ("bgr", "rgb")


def check_image_size(height: int, width: int) -> None:
    """The encoders need ``H`` and ``W`` divisible by 8 (else the 1/8 maps and ``coords_grid(H//8, W//8)`` disagree)."""
    if height % STRIDE or width % STRIDE:
        raise ValueError(
            f"image size {height}x{width} (HxW) is not a multiple of {STRIDE}; resize or crop the frames first"
        )


def normalize_images(images: torch.Tensor, channel_order: str = "bgr") -> torch.Tensor:
    """Upstream ``extract_features`` normalisation: (BGR->RGB flip), ``/255``, ImageNet mean/std.

    Args:
        images: ``(B, N, 3, H, W)`` uint8, or float in ``[0, 255]``.
        channel_order: ``"bgr"`` (upstream convention, flipped to RGB here) or ``"rgb"`` (pvslam frames).

    Returns:
        ``(B, N, 3, H, W)`` float, RGB, normalised.  Same op order as upstream (bitwise equal for float32).
    """
    if images.dim() != 5 or images.shape[2] != 3:
        raise ValueError(f"images must be (B, N, 3, H, W), got shape {tuple(images.shape)}")
    if channel_order not in CHANNEL_ORDERS:
        raise ValueError(f"channel_order must be one of {CHANNEL_ORDERS}, got {channel_order!r}")
    if channel_order == "bgr":
        images = images[:, :, [2, 1, 0]]
    x = images / 255.0  # uint8 -> float32; float stays in its dtype
    mean = torch.as_tensor(IMAGENET_MEAN, device=x.device, dtype=x.dtype)[:, None, None]
    std = torch.as_tensor(IMAGENET_STD, device=x.device, dtype=x.dtype)[:, None, None]
    return (x - mean) / std


def frames_to_images(frames: Union[Sequence[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """Stack pvslam frames (``uint8 [3, H, W]`` RGB each, or ``[N, 3, H, W]``) into ``(1, N, 3, H, W)``.

    The result is still **RGB**: pass it with ``channel_order="rgb"``.
    """
    if isinstance(frames, torch.Tensor):
        x = frames if frames.dim() == 4 else frames[None]
    else:
        x = torch.stack(list(frames), 0)
    if x.dim() != 4 or x.shape[1] != 3:
        raise ValueError(f"frames must be [3, H, W] each (or [N, 3, H, W]), got {tuple(x.shape)}")
    return x[None]


def _norm(kind: str, planes: int) -> nn.Module:
    if kind == "instance":
        return nn.InstanceNorm2d(planes)  # affine=False, track_running_stats=False (upstream defaults)
    if kind == "none":
        return nn.Identity()
    raise ValueError(f"norm must be 'instance' or 'none', got {kind!r}")


class ResidualBlock(nn.Module):
    """conv3x3-norm-ReLU-conv3x3-norm-ReLU, then ReLU(x + y); a 1x1 strided downsample when stride > 1."""

    def __init__(self, in_planes: int, planes: int, norm: str, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, kernel_size=3, padding=1, stride=stride)
        self.conv2 = nn.Conv2d(planes, planes, kernel_size=3, padding=1)
        self.relu = nn.ReLU(inplace=True)
        self.norm1 = _norm(norm, planes)
        self.norm2 = _norm(norm, planes)
        self.downsample = (
            None
            if stride == 1
            else nn.Sequential(nn.Conv2d(in_planes, planes, kernel_size=1, stride=stride), _norm(norm, planes))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        if self.downsample is not None:
            x = self.downsample(x)
        return self.relu(x + y)


class BasicEncoder(nn.Module):
    """DROID-SLAM's ``BasicEncoder``: ``(B, N, 3, H, W)`` normalised images -> ``(B, N, output_dim, H/8, W/8)``."""

    def __init__(self, output_dim: int = 128, norm: str = "instance") -> None:
        super().__init__()
        self.norm1 = _norm(norm, DIM)
        self.conv1 = nn.Conv2d(3, DIM, kernel_size=7, stride=2, padding=3)
        self.relu1 = nn.ReLU(inplace=True)
        self.layer1 = nn.Sequential(ResidualBlock(DIM, DIM, norm, 1), ResidualBlock(DIM, DIM, norm, 1))
        self.layer2 = nn.Sequential(ResidualBlock(DIM, 2 * DIM, norm, 2), ResidualBlock(2 * DIM, 2 * DIM, norm, 1))
        self.layer3 = nn.Sequential(ResidualBlock(2 * DIM, 4 * DIM, norm, 2), ResidualBlock(4 * DIM, 4 * DIM, norm, 1))
        self.conv2 = nn.Conv2d(4 * DIM, output_dim, kernel_size=1)
        # Upstream init (only matters for training from scratch; checkpoints overwrite it).
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c, h, w = x.shape
        x = x.reshape(b * n, c, h, w)
        x = self.relu1(self.norm1(self.conv1(x)))
        x = self.layer3(self.layer2(self.layer1(x)))
        x = self.conv2(x)
        return x.reshape(b, n, *x.shape[1:])
