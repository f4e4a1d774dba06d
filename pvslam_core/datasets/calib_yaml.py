"""Calibration from OpenCV FileStorage files (YAML or XML), parsed with ``cv2.FileStorage``.

Three layouts, tried in this order:

* **ORB-SLAM3** (``Camera.type: "PinHole"``): ``Camera1.fx/fy/cx/cy``, optional ``Camera1.k1 k2 p1 p2 [k3]``;
  ``Camera.width`` / ``Camera.height``.  Fisheye models (``KannalaBrandt8``) are refused: the readers undistort
  with the pinhole + radial-tangential model only.
* **ORB-SLAM2** (also pySLAM's settings files): ``Camera.fx/fy/cx/cy``, optional ``Camera.k1 k2 p1 p2 [k3]``,
  ``Camera.width`` / ``Camera.height``.
* **OpenCV** (``calibrateCamera`` samples, ROS ``camera_calibration``): ``camera_matrix`` (3x3, an
  ``!!opencv-matrix`` or a map with ``data``), ``distortion_coefficients`` (4, 5, 8, 12 or 14 values), optional
  ``image_width`` / ``image_height``.

ORB-SLAM files start with ``%YAML:1.0``; a file without that header is read as YAML all the same.  When the file
gives an image size that differs from the images', the intrinsics are scaled to the images if the aspect ratio is
the same (a calibration made at another resolution of the same sensor) and refused otherwise; distortion
coefficients act on normalised coordinates and do not change.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Optional

import numpy as np

from ..types import Intrinsics
from .base import DatasetError

ORB_KEYS = ("fx", "fy", "cx", "cy")
ORB_DIST = ("k1", "k2", "p1", "p2", "k3")
MATRIX_KEYS = ("camera_matrix", "cameraMatrix", "K")
DIST_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")


def _open(path: Path, text: str):
    import cv2

    body = text
    if not body.lstrip().startswith(("%YAML", "<?xml", "<opencv_storage", "{")):
        body = "%YAML:1.0\n" + body  # FileStorage guesses the format from this header
    try:
        fs = cv2.FileStorage(body, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:  # some parse errors surface as SystemError from the binding
        cause = exc.__cause__ or exc
        msg = str(cause).strip().splitlines()[-1] if str(cause).strip() else type(cause).__name__
        msg = re.sub(r"^.*?error: \(-?\d+:[^)]*\)\s*", "", msg)  # drop OpenCV's source-file prefix
        raise DatasetError(f"{path}: not a readable YAML/XML calibration ({msg})") from None
    if not fs.isOpened():
        raise DatasetError(f"{path}: not a readable YAML/XML calibration")
    return fs


def _number(fs, key: str, path: Path) -> Optional[float]:
    node = fs.getNode(key)
    if node.isNone():
        return None
    if not (node.isReal() or node.isInt()):
        raise DatasetError(f"{path}: {key} must be a number, got {node.string() or 'a ' + _kind(node)!r}")
    v = float(node.real())
    if not math.isfinite(v):
        raise DatasetError(f"{path}: {key}={v} is not a finite number")
    return v


def _kind(node) -> str:
    return "map" if node.isMap() else "sequence" if node.isSeq() else "string" if node.isString() else "value"


def _array(fs, keys: tuple[str, ...], path: Path) -> tuple[Optional[str], Optional[np.ndarray]]:
    """The first of ``keys`` present, as a flat float64 array (an opencv-matrix, a sequence or a map with data)."""
    for key in keys:
        node = fs.getNode(key)
        if node.isNone():
            continue
        if node.isMap() and node.getNode("data").isNone():
            mat = node.mat()
            if mat is None:
                raise DatasetError(f"{path}: {key} is a map without 'data'")
            return key, np.asarray(mat, np.float64).reshape(-1)
        if node.isMap():
            node = node.getNode("data")
        if node.isSeq():
            vals = [node.at(i).real() for i in range(node.size())]
            return key, np.asarray(vals, np.float64)
        mat = node.mat()
        if mat is None:
            raise DatasetError(f"{path}: {key} is not a matrix or a list of numbers")
        return key, np.asarray(mat, np.float64).reshape(-1)
    return None, None


def _orb(fs, prefix: str, path: Path) -> Optional[tuple[list[float], list[float]]]:
    vals = [_number(fs, f"{prefix}.{k}", path) for k in ORB_KEYS]
    if all(v is None for v in vals):
        return None
    missing = [f"{prefix}.{k}" for k, v in zip(ORB_KEYS, vals) if v is None]
    if missing:
        raise DatasetError(f"{path}: missing {', '.join(missing)}")
    dist = [_number(fs, f"{prefix}.{k}", path) for k in ORB_DIST]
    if dist[4] is None:
        dist = dist[:4]
    if all(d is None for d in dist):
        return vals, []
    if any(d is None for d in dist):
        missing = [f"{prefix}.{k}" for k, d in zip(ORB_DIST, dist) if d is None]
        raise DatasetError(f"{path}: incomplete distortion: missing {', '.join(missing)} "
                           f"(give {prefix}.k1 k2 p1 p2 [k3], or none of them)")
    return vals, dist


def intrinsics_from_filestorage(path: Path, text: str, width: int, height: int) -> Intrinsics:
    """Parse an ORB-SLAM or OpenCV calibration file (see the module doc) for ``width`` x ``height`` images."""
    fs = _open(path, text)
    try:
        cam_type = fs.getNode("Camera.type")
        model = cam_type.string() if not cam_type.isNone() else ""
        if model and model not in ("PinHole", "Pinhole", "pinhole", "Rectified"):
            raise DatasetError(f"{path}: Camera.type {model!r} is not supported (only PinHole: the readers undistort "
                               "with the radial-tangential model)")
        found = _orb(fs, "Camera1", path) or _orb(fs, "Camera", path)
        if found is not None:
            (fx, fy, cx, cy), dist = found
            size = (_number(fs, "Camera.width", path), _number(fs, "Camera.height", path))
        else:
            mkey, m = _array(fs, MATRIX_KEYS, path)
            if m is None:
                raise DatasetError(f"{path}: no camera intrinsics found: expected Camera.fx/fy/cx/cy (ORB-SLAM2), "
                                   "Camera1.fx/... (ORB-SLAM3) or camera_matrix (OpenCV); keys in the file: "
                                   + (", ".join(fs.root().keys()) or "(none)"))
            if m.size != 9:
                raise DatasetError(f"{path}: {mkey} must be a 3x3 matrix, found {m.size} values")
            if not np.all(np.isfinite(m)):
                raise DatasetError(f"{path}: {mkey} holds a value that is not a finite number")
            fx, fy, cx, cy = float(m[0]), float(m[4]), float(m[2]), float(m[5])
            dkey, d = _array(fs, DIST_KEYS, path)
            dist = [] if d is None else [float(v) for v in d]
            if dist and len(dist) not in (4, 5, 8, 12, 14):
                raise DatasetError(f"{path}: {dkey} must have 4, 5, 8, 12 or 14 values, found {len(dist)}")
            size = (_number(fs, "image_width", path), _number(fs, "image_height", path))
    finally:
        fs.release()
    if size[0] and size[1] and (int(size[0]), int(size[1])) != (int(width), int(height)):
        cw, ch = int(size[0]), int(size[1])
        if abs(cw / ch - width / height) > 0.01 * width / height:
            raise DatasetError(f"{path}: the calibration is for {cw}x{ch} images but the images are "
                               f"{width}x{height} (another aspect ratio: a different crop or camera)")
        sx, sy = width / cw, height / ch  # same sensor at another resolution: scale (pixel centres at integers)
        fx, fy, cx, cy = fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5
    try:
        return Intrinsics(fx, fy, cx, cy, int(width), int(height), tuple(dist))
    except ValueError as exc:
        raise DatasetError(f"{path}: invalid calibration: {exc}") from exc
