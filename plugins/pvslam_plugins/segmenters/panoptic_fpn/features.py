"""PanopticFPN's batched feature pyramid (internal to the model; consumed by its own heads and a VPS fusion head).

The public, per-image type is the core's :class:`pvslam_core.types.FeaturePyramid` (``PanopticSegmentation.
features``); :meth:`PyramidBatch.to_core` converts one image of a batch to it.  A :class:`PyramidBatch` is an
ordered mapping ``level name -> tensor [B, C, h, w]`` with each level's stride, plus the geometry needed to relate
a feature cell to a pixel of the original frame: the network input size (after the test resize, before padding)
and the frame size per image.  Feature cell ``(i, j)`` of a level with stride ``s``
covers input pixels ``[j*s, (j+1)*s) x [i*s, (i+1)*s)``; input pixel ``x`` is frame pixel
``(x + 0.5) * W_frame / w_input - 0.5``.  A VPS head that fuses features builds a new pyramid with
:meth:`PyramidBatch.replace` and feeds it to ``PanopticFPN.decode``: same geometry, new tensors.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Mapping

import torch

from pvslam_core.types import FeaturePyramid

__all__ = ["PyramidBatch"]


@dataclass
class PyramidBatch(Mapping[str, torch.Tensor]):
    levels: dict[str, torch.Tensor]  # name -> float [B, C, h, w], finest level first
    strides: dict[str, int]  # name -> stride in network-input pixels
    image_sizes: list[tuple[int, int]]  # per image (h, w) of the network input, before padding
    output_sizes: list[tuple[int, int]] = field(default_factory=list)  # per image (H, W) of the original frame

    def __post_init__(self) -> None:
        if set(self.levels) != set(self.strides):
            raise ValueError(f"PyramidBatch: levels {list(self.levels)} and strides {list(self.strides)} differ")
        if not self.output_sizes:
            self.output_sizes = list(self.image_sizes)
        batch = {int(t.shape[0]) for t in self.levels.values()}
        if len(batch) > 1 or (batch and batch.pop() != len(self.image_sizes)):
            shapes = {k: tuple(v.shape) for k, v in self.levels.items()}
            raise ValueError(f"PyramidBatch: batch sizes of {shapes} do not match {len(self.image_sizes)} images")
        if len(self.output_sizes) != len(self.image_sizes):
            raise ValueError("PyramidBatch: one output size per image is needed")

    def __getitem__(self, name: str) -> torch.Tensor:
        return self.levels[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self.levels)

    def __len__(self) -> int:
        return len(self.levels)

    def stride(self, name: str) -> int:
        return self.strides[name]

    def select(self, names: list[str] | tuple[str, ...]) -> list[torch.Tensor]:
        missing = [n for n in names if n not in self.levels]
        if missing:
            raise KeyError(f"PyramidBatch has no level(s) {missing}; it has {list(self.levels)}")
        return [self.levels[n] for n in names]

    def replace(self, levels: Mapping[str, torch.Tensor]) -> "PyramidBatch":
        """Same geometry, new tensors (e.g. fused features); every level's shape must stay the same."""
        if set(levels) != set(self.levels):
            raise ValueError(f"replace: expected levels {list(self.levels)}, got {list(levels)}")
        for k, v in levels.items():
            old = self.levels[k]
            if v.shape[0] != old.shape[0] or v.shape[2:] != old.shape[2:]:
                raise ValueError(f"replace: level {k} has shape {tuple(v.shape)}, expected {tuple(old.shape)} "
                                 "(channels may differ, batch and size may not)")
        return PyramidBatch({k: levels[k] for k in self.levels}, dict(self.strides), list(self.image_sizes),
                            list(self.output_sizes))

    def image(self, i: int) -> "PyramidBatch":
        """The pyramid of image ``i`` of the batch (views, no copy)."""
        return PyramidBatch({k: v[i:i + 1] for k, v in self.levels.items()}, dict(self.strides),
                            [self.image_sizes[i]], [self.output_sizes[i]])

    def to_core(self, i: int = 0) -> FeaturePyramid:
        """Image ``i`` as the core's per-image :class:`~pvslam_core.types.FeaturePyramid` (maps ``[C, h, w]``,
        views).  Strides count network-input pixels: equal to frame pixels unless the preset resizes at test time
        (then one input pixel is ``output_sizes[i][1] / image_sizes[i][1]`` frame pixels)."""
        return FeaturePyramid({k: v[i] for k, v in self.levels.items()}, dict(self.strides))
