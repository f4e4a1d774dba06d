"""The ``npz`` reader: images, timestamps, intrinsics and optional ground-truth poses in one file."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np
import torch
from pydantic import Field

from pvslam_core.datasets.base import BaseReader, DatasetError, ReaderOptions
from pvslam_core.types import Frame, Intrinsics


class NpzConfig(ReaderOptions):
    path: str = Field(..., description="the .npz file")


class NpzReader(BaseReader):
    def __init__(self, config: NpzConfig):
        self.path = Path(config.path)
        if not self.path.is_file():
            raise DatasetError(f"{self.path}: npz sequence not found")
        try:
            data = np.load(self.path)
            self.images = data["images"]
            self.timestamps = data["timestamps"].astype(np.float64)
            self.intr = data["intrinsics"].astype(np.float64)
            self.poses = data["poses"].astype(np.float64) if "poses" in data.files else None
        except (KeyError, ValueError, OSError) as exc:
            raise DatasetError(f"{self.path}: not a pvslam npz sequence ({exc}); need images, timestamps, intrinsics")
        if self.images.ndim != 4 or self.images.shape[-1] != 3 or self.images.dtype != np.uint8:
            raise DatasetError(f"{self.path}: images must be uint8 [N, H, W, 3], got {self.images.dtype} {self.images.shape}")
        if len(self.timestamps) != len(self.images) or self.intr.shape != (4,):
            raise DatasetError(f"{self.path}: need one timestamp per image and intrinsics [fx, fy, cx, cy]")
        super().__init__(config)

    def _raw_count(self) -> int:
        return len(self.images)

    def _raw_intrinsics(self) -> Intrinsics:
        h, w = self.images.shape[1:3]
        fx, fy, cx, cy = (float(v) for v in self.intr)
        return Intrinsics(fx, fy, cx, cy, width=w, height=h)

    def _load(self, raw_index: int) -> Frame:
        img = torch.from_numpy(np.ascontiguousarray(self.images[raw_index])).permute(2, 0, 1).contiguous()
        pose = torch.from_numpy(self.poses[raw_index]) if self.poses is not None else None
        return Frame(raw_index, float(self.timestamps[raw_index]), img, self._raw_intrinsics(), gt_pose=pose,
                     name=f"{self.path.name}[{raw_index}]")

    def _sequence_name(self) -> str:
        return self.path.stem

    def _has_gt(self) -> tuple[bool, bool, bool]:
        return (self.poses is not None, False, False)


def write_npz(path, frames: Iterable[Frame]) -> Path:
    frames = list(frames)
    if not frames:
        raise ValueError("no frames to write")
    k = frames[0].intrinsics
    data = {
        "images": np.stack([f.image_hwc() for f in frames]),
        "timestamps": np.array([f.timestamp for f in frames]),
        "intrinsics": np.array([k.fx, k.fy, k.cx, k.cy]),
    }
    if all(f.gt_pose is not None for f in frames):
        data["poses"] = np.stack([f.gt_pose.double().numpy() for f in frames])
    np.savez(path, **data)
    return Path(path)
