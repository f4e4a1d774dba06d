"""Configuration of the image-folder reader."""
from __future__ import annotations

from typing import Literal, Optional, Union

from pydantic import Field

from pvslam_core.datasets.base import ReaderOptions


class ImagesConfig(ReaderOptions):
    path: str = Field(..., description="folder of images (png/jpg...), read in natural order (2 before 10)")
    calib: Optional[Union[str, list[float]]] = Field(
        None,
        description="calibration file, or [fx, fy, cx, cy, (k1, k2, p1, p2, (k3))]; default: calib.txt in the "
        "folder or its parent",
    )
    fps: float = Field(10.0, gt=0, description="frame rate for timestamps when timestamps='fps'")
    timestamps: Literal["fps", "filename"] = Field(
        "fps", description="'fps': index / fps; 'filename': the numeric file name (seconds, or ns when > 1e15)"
    )
    groundtruth: Optional[str] = Field(None, description="TUM trajectory file associated by timestamp")
    gt_max_diff: float = Field(0.02, ge=0, description="max timestamp difference (s) for ground truth")
    follow: bool = Field(
        False, description="a folder that is still being written (a camera dumping frames): read images as they "
        "appear, in natural order, until none has appeared for `wait_timeout` seconds; the length is unknown")
    wait_timeout: float = Field(5.0, gt=0, description="follow: seconds without a new image that end the sequence "
                                "(also how long to wait for the first image)")
