"""Configuration of the EuRoC MAV reader."""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from pvslam_core.datasets.base import ReaderOptions


class EurocConfig(ReaderOptions):
    path: str = Field(..., description="sequence folder that contains mav0/ (e.g. MH_01_easy)")
    camera: Literal["cam0", "cam1"] = Field("cam0", description="which camera of the stereo pair")
    gt_max_diff: float = Field(0.005, ge=0, description="max |t_frame - t_gt| (s) to attach a ground-truth pose")
