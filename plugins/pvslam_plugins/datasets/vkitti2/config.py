"""Configuration of the Virtual KITTI 2 reader."""
from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from pvslam_core.datasets.base import ReaderOptions


class Vkitti2Config(ReaderOptions):
    path: str = Field(..., description="root holding SceneNN/<variation>/ (or the unpacked vkitti_2.0.3_* archives)")
    scene: str = Field("Scene01", description="Scene01, Scene02, Scene06, Scene18 or Scene20 ('01' and 1 also work)")
    variation: str = Field("clone", description="clone, 15-deg-left, 15-deg-right, 30-deg-left, fog, morning, ...")
    camera: Literal[0, 1] = Field(0, description="Camera_0 (left) or Camera_1 (right)")
    fps: float = Field(10.0, gt=0, description="frame rate for timestamps (VKITTI2 clones KITTI's 10 Hz)")

    @field_validator("scene", mode="before")
    @classmethod
    def _scene_name(cls, v: object) -> object:
        if isinstance(v, int) or (isinstance(v, str) and v.isdigit()):
            return f"Scene{int(v):02d}"
        return v
