"""Configuration of the video-file reader."""
from __future__ import annotations

from typing import Literal, Optional, Union

from pydantic import Field

from pvslam_core.datasets.base import ReaderOptions


class VideoConfig(ReaderOptions):
    path: str = Field(..., description="video file readable by OpenCV (avi, mp4, mkv, ...), or a camera index "
                      "('0': the first camera; its length is unknown: the run ends with the camera, "
                      "run.max_frames or Ctrl-C)")
    calib: Optional[Union[str, list[float]]] = Field(
        None,
        description="calibration file, or [fx, fy, cx, cy, (k1, k2, p1, p2, (k3))]; default: calib.txt beside "
        "the video (required)",
    )
    timestamps: Literal["msec", "fps"] = Field(
        "msec", description="'msec': each frame's container time (CAP_PROP_POS_MSEC; a camera: the wall clock); "
        "'fps': index / fps"
    )
    fps: Optional[float] = Field(None, gt=0, description="frame rate; default: the container's")
