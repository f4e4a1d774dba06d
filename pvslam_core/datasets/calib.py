"""Calibration files: DROID-SLAM's one-line format, ORB-SLAM / OpenCV YAML, and calibration values in configs.

* **Values** (DROID-SLAM's ``calib.txt``): ``fx fy cx cy [k1 k2 p1 p2 [k3 [k4 k5 k6]]]`` -- 4, 8, 9 or 12 numbers,
  the counts DROID-SLAM's demo passes to ``cv2.undistort`` (OpenCV's 4, 5 and 8 distortion coefficients).  Values
  are separated by whitespace and/or commas; lines starting with ``#`` and blank lines are ignored.  The image size
  is not part of the file: the caller supplies it (usually from the first image).
* **YAML / XML** (ORB-SLAM2 ``Camera.fx``..., ORB-SLAM3 ``Camera1.fx``..., OpenCV FileStorage ``camera_matrix`` /
  ``distortion_coefficients``): see :mod:`pvslam_core.datasets.calib_yaml`.
* **KITTI projection rows** (odometry ``calib.txt``: ``P0: 12 numbers`` ...; raw ``calib_cam_to_cam.txt``:
  ``P_rect_02: ...``): the row of the camera in use, see :mod:`pvslam_core.datasets.calib_kitti`.

:func:`read_calibration` tells the formats apart by content; anything else is an error that names the file and
lists what was expected.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Optional, Sequence

from ..types import Intrinsics
from .base import DatasetError
from .calib_kitti import intrinsics_from_projection_file, is_projection_text

_SPLIT = re.compile(r"[\s,]+")
VALID_COUNTS = (4, 8, 9, 12)
VALUE_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
VALUES_FORMAT = "fx fy cx cy [k1 k2 p1 p2 [k3 [k4 k5 k6]]]"
#: what a calibration file may be, for error messages
EXPECTED_FORMATS = (f"one line '{VALUES_FORMAT}' (DROID-SLAM), an ORB-SLAM YAML (Camera.fx ... or Camera1.fx ...), "
                    "an OpenCV FileStorage YAML/XML with camera_matrix and distortion_coefficients, or KITTI "
                    "projection rows (P0: 12 numbers ... / P_rect_02: 12 numbers)")


def intrinsics_from_values(values: Sequence[float], width: int, height: int, source: str = "calib") -> Intrinsics:
    """``[fx, fy, cx, cy, (k1, k2, p1, p2, (k3, (k4, k5, k6)))]`` -> :class:`Intrinsics`; errors name ``source``."""
    vals = [float(v) for v in values]
    if len(vals) not in VALID_COUNTS:
        raise DatasetError(
            f"{source}: expected 4, 8, 9 or 12 calibration values ({VALUES_FORMAT}), found {len(vals)}"
        )
    try:
        return Intrinsics(vals[0], vals[1], vals[2], vals[3], int(width), int(height), tuple(vals[4:]))
    except ValueError as exc:
        raise DatasetError(f"{source}: invalid calibration: {exc}") from exc


def read_calibration_values(path: str | Path) -> list[float]:
    """The numbers of a values-format calibration file (all non-comment lines together)."""
    p = Path(path)
    return _values_from_text(p, _read_text(p))


def _read_text(p: Path) -> str:
    if not p.is_file():
        raise DatasetError(f"{p}: calibration file not found" + (" (it is a folder)" if p.is_dir() else ""))
    try:
        return p.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise DatasetError(f"{p}: not a text file; expected {EXPECTED_FORMATS}") from None


def _values_from_text(p: Path, text: str, hint: bool = False) -> list[float]:
    vals: list[float] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        for tok in _SPLIT.split(s):
            if not tok:
                continue
            try:
                v = float(tok)
            except ValueError:
                more = f"; expected {EXPECTED_FORMATS}" if hint else ""
                raise DatasetError(f"{p}:{lineno}: not a number: {tok!r}{more}") from None
            if not math.isfinite(v):  # float() accepts 'inf' and 'nan'; the pipeline would fail much later
                raise DatasetError(f"{p}:{lineno}: {_value_name(len(vals))}={v} is not a finite number")
            vals.append(v)
    return vals


_KEY_LINE = re.compile(r"^\s*[A-Za-z_][\w.\-]*\s*:")


def is_structured(path: Path, text: str) -> bool:
    """Whether a calibration file is YAML/XML (FileStorage) rather than plain values."""
    if path.suffix.lower() in (".yaml", ".yml", ".xml"):
        return True
    head = text.lstrip()
    return head.startswith(("%YAML", "<?xml", "<opencv_storage")) or any(
        _KEY_LINE.match(line) for line in text.splitlines() if not line.lstrip().startswith("#"))


def _value_name(k: int) -> str:
    return VALUE_NAMES[k] if k < len(VALUE_NAMES) else f"value {k + 1}"


def read_calibration(path: str | Path, width: int, height: int, camera: Optional[int] = None) -> Intrinsics:
    """The intrinsics in ``path`` (values, ORB-SLAM or OpenCV YAML/XML, KITTI projection rows) for an image of
    ``width`` x ``height``; ``camera`` picks a KITTI file's row (``P2`` / ``P_rect_02`` for 2; None: P0)."""
    p = Path(path)
    text = _read_text(p)
    if is_projection_text(text):
        return intrinsics_from_projection_file(p, text, width, height, camera)
    if is_structured(p, text):
        from .calib_yaml import intrinsics_from_filestorage

        return intrinsics_from_filestorage(p, text, width, height)
    vals = _values_from_text(p, text, hint=True)
    if not vals:
        raise DatasetError(f"{p}: no calibration values; expected {EXPECTED_FORMATS}")
    return intrinsics_from_values(vals, width, height, source=str(p))


def calibration_from_option(
    calib: "str | Path | Sequence[float] | None", width: int, height: int, search: Sequence[Path] = (),
    owner: str = "reader", camera: Optional[int] = None,
) -> Intrinsics:
    """A reader's ``calib`` option: values, a file path, or None (then the first ``calib.txt`` in ``search``);
    ``camera``: the KITTI camera whose projection row a KITTI file gives (see :func:`read_calibration`)."""
    if calib is None:
        for d in search:
            p = Path(d) / "calib.txt"
            if p.is_file():
                return read_calibration(p, width, height, camera)
        where = ", ".join(str(Path(d) / "calib.txt") for d in search) or "(nowhere)"
        raise DatasetError(
            f"{owner}: no calibration: set 'calib' (--calib) to a file or to [fx, fy, cx, cy, (k1, k2, p1, p2, "
            "(k3, (k4, k5, k6)))]; "
            f"looked for {where}"
        )
    if isinstance(calib, (str, Path)):
        return read_calibration(Path(calib).expanduser(), width, height, camera)
    return intrinsics_from_values(list(calib), width, height, source=f"{owner} config 'calib'")
