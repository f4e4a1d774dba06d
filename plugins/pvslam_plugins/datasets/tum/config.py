"""Configuration of the TUM RGB-D reader."""
from __future__ import annotations

from typing import Optional, Union

from pydantic import Field

from pvslam_core.datasets.base import ReaderOptions


class TumConfig(ReaderOptions):
    path: str = Field(..., description="sequence folder with rgb.txt (depth.txt, groundtruth.txt optional)")
    calib: Optional[Union[str, list[float]]] = Field(
        None, description="calibration file (values, ORB-SLAM or OpenCV YAML) or [fx, fy, cx, cy, (k1, k2, p1, p2, "
        "(k3))]; overrides calib.txt and the freiburg presets"
    )
    max_diff: float = Field(0.02, ge=0, description="max timestamp difference (s) for depth and ground truth")
    depth_scale: float = Field(5000.0, gt=0, description="depth PNG value per metre")
