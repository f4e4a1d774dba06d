"""Configuration of the KITTI odometry reader."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from pvslam_core.datasets.base import ReaderOptions


class KittiConfig(ReaderOptions):
    path: str = Field(..., description="dataset root holding sequences/NN/ (and poses/NN.txt), or a sequence folder "
                      "itself (image_0|image_2 + calib.txt), wherever it is")
    sequence: str = Field("00", description="sequence number, e.g. '06' (ignored when path is a sequence folder)")
    calib: Optional[str] = Field(None, description="file of P0..P3 rows (KITTI's calib.txt); default: calib.txt in "
                                 "the sequence folder (KITTI ships it in a separate archive)")
    camera: Literal["image_0", "image_1", "image_2", "image_3"] = Field(
        "image_0", description="image folder (image_0/1 grayscale, image_2/3 colour); intrinsics from P0..P3"
    )
    fps: float = Field(10.0, gt=0, description="frame rate used when times.txt is missing")
