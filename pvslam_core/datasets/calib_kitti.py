"""KITTI's projection-matrix calibration files: ``NAME: 12 numbers`` lines, each a 3x4 row-major matrix.

* odometry ``calib.txt``: ``P0:`` .. ``P3:`` (one per camera: image_0/1 grey, image_2/3 colour) and ``Tr:``;
* raw ``calib_cam_to_cam.txt``: ``P_rect_00:`` .. ``P_rect_03:`` among lines of other shapes (``calib_time``,
  ``S_00`` (2 numbers), ``K_00`` (9), ...), which are skipped.

Camera k's intrinsics are ``fx = P[0,0], fy = P[1,1], cx = P[0,2], cy = P[1,2]`` of its row; the images are
rectified (no distortion).  :func:`intrinsics_from_projection_file` takes the row of the camera in use and says
which on the ``pvslam.notice`` logger.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Optional

import numpy as np

from ..types import Intrinsics
from .base import DatasetError

NOTICE = logging.getLogger("pvslam.notice")
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_ROW_LINE = re.compile(rf"^\s*(P\d|P_rect_\d\d)\s*:\s*(?:{_NUM}\s+){{11}}{_NUM}\s*$")
_ROW_NAME = re.compile(r"^(P\d|P_rect_\d\d)$")
_CAMERA_FOLDER = re.compile(r"^image_(\d)$|^image_0(\d)$")
FORMAT = "KITTI projection rows ('P0: 12 numbers' ... or 'P_rect_02: 12 numbers')"


def is_projection_text(text: str) -> bool:
    """Whether a calibration file holds KITTI projection rows (a ``P0:`` / ``P_rect_02:`` line of 12 numbers)."""
    return any(_ROW_LINE.match(line) for line in text.splitlines())


def read_projection_matrices(path: Path, text: Optional[str] = None) -> dict[str, np.ndarray]:
    """``{"P0": 3x4, ..., "Tr": 3x4, "P_rect_02": 3x4}`` from ``NAME: 12 numbers`` lines; lines with another number
    of values or non-numeric values are skipped, except projection rows (``P0``, ``P_rect_02``): those are errors
    that name the file, the line and the count."""
    path = Path(path)
    if text is None:
        if not path.is_file():
            raise DatasetError(f"{path}: calibration file not found")
        text = path.read_text()
    out: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        if ":" not in line:
            raise DatasetError(f"{path}:{lineno}: expected 'NAME: 12 numbers', got {line.strip()!r}")
        key, vals = (s.strip() for s in line.split(":", 1))
        strict = bool(_ROW_NAME.match(key)) or key == "Tr"
        try:
            nums = [float(v) for v in vals.split()]
        except ValueError:
            if strict:
                raise DatasetError(f"{path}:{lineno}: non-numeric value in {key}") from None
            continue
        if len(nums) != 12:
            if strict:
                raise DatasetError(f"{path}:{lineno}: {key} needs 12 values (3x4 matrix), found {len(nums)}")
            continue
        out[key] = np.asarray(nums, dtype=np.float64).reshape(3, 4)
    return out


def intrinsics_from_projection(P: np.ndarray, width: int, height: int, source: str) -> Intrinsics:
    """The pinhole intrinsics of a 3x4 projection matrix ``K [R | t]`` (no distortion); errors name ``source``."""
    try:
        return Intrinsics(float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2]), int(width), int(height))
    except ValueError as exc:
        raise DatasetError(f"{source}: {exc}") from exc


def camera_from_folder(folder: Optional[Path]) -> Optional[int]:
    """The KITTI camera of an image folder: ``image_2`` (odometry) or ``image_02[/data]`` (raw) -> 2; else None."""
    if folder is None:
        return None
    folder = Path(folder)
    m = _CAMERA_FOLDER.match(folder.parent.name if folder.name == "data" else folder.name)
    return int(m.group(1) or m.group(2)) if m else None


def intrinsics_from_projection_file(path: Path, text: str, width: int, height: int,
                                    camera: Optional[int] = None) -> Intrinsics:
    """The intrinsics of camera ``camera``'s row (``P{camera}`` or ``P_rect_0{camera}``); without a camera, P0 /
    P_rect_00 (else the file's first row).  Which row was taken goes to the ``pvslam.notice`` logger."""
    mats = read_projection_matrices(path, text)
    rows = [k for k in mats if _ROW_NAME.match(k)]
    want = 0 if camera is None else camera
    name = next((k for k in (f"P{want}", f"P_rect_{want:02d}") if k in mats), None)
    if name is None and camera is not None:
        raise DatasetError(f"{path}: no P{camera} or P_rect_{camera:02d} row for camera image_{camera} "
                           f"(the file has: {', '.join(rows) or 'no projection rows'})")
    why = f"camera image_{camera}, from the image folder's name" if camera is not None else "the default camera"
    if name is None:
        if not rows:
            raise DatasetError(f"{path}: no projection rows; expected {FORMAT}")
        name, why = rows[0], "the file's first projection row"
    NOTICE.info("calibration: %s: KITTI projection row %s (%s)", path, name, why)
    return intrinsics_from_projection(mats[name], width, height, f"{path}: {name}")
