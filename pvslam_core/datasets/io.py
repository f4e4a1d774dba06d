"""Small file helpers shared by the dataset readers (errors always name the file)."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch

from .base import DatasetError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")


def natural_key(name: str) -> list:
    """Sort key that orders ``frame2`` before ``frame10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: str | Path, extensions: Sequence[str] = IMAGE_EXTENSIONS) -> list[Path]:
    """Image files directly inside ``folder``, sorted naturally."""
    d = Path(folder)
    if not d.is_dir():
        raise DatasetError(f"{d}: image folder not found")
    exts = {e.lower() for e in extensions}
    files = [p for p in d.iterdir() if p.is_file() and p.suffix.lower() in exts]
    return sorted(files, key=lambda p: natural_key(p.name))


def _imread(path: Path, flags: int) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise DatasetError(f"{path}: file missing")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None:
        raise DatasetError(f"{path}: unreadable or corrupt image")
    return img


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an image file."""
    import cv2

    img = _imread(Path(path), cv2.IMREAD_UNCHANGED)
    return int(img.shape[1]), int(img.shape[0])


def to_chw_rgb(img: np.ndarray, source: str = "image") -> torch.Tensor:
    """Any OpenCV-decoded array (gray, BGR, BGRA; 8 or 16 bit) -> ``uint8 [3, H, W]`` RGB tensor.

    Built with numpy copies (a torch ``permute().contiguous()`` of a full frame is several times slower).
    """
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise DatasetError(f"{source}: unsupported image type {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 2:
        chw = np.repeat(img[None], 3, axis=0)
    elif img.shape[2] in (3, 4):
        chw = np.ascontiguousarray(img[:, :, 2::-1].transpose(2, 0, 1))  # BGR(A) -> RGB, HWC -> CHW
    else:
        raise DatasetError(f"{source}: unsupported channel count {img.shape[2]}")
    return torch.from_numpy(chw)


def read_rgb(path: str | Path) -> torch.Tensor:
    """``uint8 [3, H, W]`` RGB (grayscale replicated to 3 channels)."""
    import cv2

    p = Path(path)
    return to_chw_rgb(_imread(p, cv2.IMREAD_UNCHANGED), str(p))


def read_raw(path: str | Path) -> np.ndarray:
    """The image array exactly as stored (16-bit kept, BGR order for colour)."""
    import cv2

    return _imread(Path(path), cv2.IMREAD_UNCHANGED)


def read_depth_png(path: str | Path, scale: float, invalid: int | None = None) -> torch.Tensor:
    """16-bit depth PNG -> ``float32 [H, W]`` metres (value / ``scale``); 0 and ``invalid`` -> 0."""
    p = Path(path)
    raw = read_raw(p)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DatasetError(f"{p}: expected a single-channel 16-bit depth PNG, got {raw.dtype} {raw.shape}")
    d = raw.astype(np.float32) / float(scale)
    if invalid is not None:
        d[raw == invalid] = 0.0
    return torch.from_numpy(d)


def check_timestamps(ts: np.ndarray, path: str | Path) -> None:
    """Raise naming the file if timestamps are not strictly increasing."""
    ts = np.asarray(ts)
    if ts.size > 1:
        diff = np.diff(ts)
        bad = np.nonzero(diff <= 0)[0]
        if bad.size:
            i = int(bad[0])
            kind = "duplicate" if diff[i] == 0 else "unsorted"
            raise DatasetError(
                f"{path}: {kind} timestamps at entries {i} and {i + 1} ({float(ts[i])!r}, {float(ts[i + 1])!r}); "
                "timestamps must be strictly increasing"
            )


def read_file_list(path: str | Path, parse: Callable[[str], Any] = float, dtype: Any = np.float64,
                   what: str = "timestamp") -> tuple[np.ndarray, list[str]]:
    """``timestamp filename`` lists (TUM's rgb.txt, EuRoC's data.csv; ``#`` comments, spaces or commas) ->
    (timestamps [N] as ``dtype``, names); checks sortedness. ``parse`` reads one timestamp (EuRoC passes an
    exact integer-nanosecond parser: float64 cannot hold 19-digit nanoseconds)."""
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: file list not found")
    ts: list[Any] = []
    names: list[str] = []
    for lineno, line in enumerate(p.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) < 2:
            raise DatasetError(f"{p}:{lineno}: expected '{what} filename', got {s!r}")
        try:
            ts.append(parse(parts[0]))
        except ValueError:
            raise DatasetError(f"{p}:{lineno}: not a {what}: {parts[0]!r}") from None
        names.append(parts[1])
    arr = np.asarray(ts, dtype=dtype)
    check_timestamps(arr, p)
    return arr, names


def associate_nearest(query: np.ndarray, ref: np.ndarray, max_diff: float) -> np.ndarray:
    """For each query time the index of the nearest ``ref`` time (sorted), or -1 if farther than ``max_diff``."""
    query = np.asarray(query, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    out = np.full(query.shape, -1, dtype=np.int64)
    if ref.size == 0 or query.size == 0:
        return out
    pos = np.searchsorted(ref, query)
    lo = np.clip(pos - 1, 0, ref.size - 1)
    hi = np.clip(pos, 0, ref.size - 1)
    pick = np.where(np.abs(ref[lo] - query) <= np.abs(ref[hi] - query), lo, hi)
    ok = np.abs(ref[pick] - query) <= max_diff
    out[ok] = pick[ok]
    return out


def associate_poses(
    frame_ts: np.ndarray, gt_ts: np.ndarray, gt_poses: np.ndarray, max_diff: float
) -> Optional[np.ndarray]:
    """Ground-truth pose per frame by nearest timestamp: ``[N, 7]`` with NaN rows where none is within
    ``max_diff``; None when no frame has one."""
    idx = associate_nearest(frame_ts, gt_ts, max_diff)
    if not (idx >= 0).any():
        return None
    out = np.full((len(idx), 7), np.nan)
    out[idx >= 0] = gt_poses[idx[idx >= 0]]
    return out


def pose_at(poses: Optional[np.ndarray], i: int) -> Optional[torch.Tensor]:
    """Row ``i`` of a per-frame pose array as a float64 tensor, or None (no array, or a NaN row)."""
    if poses is None or np.isnan(poses[i, 0]):
        return None
    return torch.from_numpy(poses[i].copy())
