"""A camera's auto-exposure applied to a sequence folder.

The renderer draws every frame at one exposure; real cameras change it (a tunnel exit, a sunlit facade).
:func:`exposure_copy` writes a copy of a sequence folder whose ``rgb/`` images follow :func:`auto_exposure_gain`
(the other entries are symlinks to the original's): the same scene under a changing exposure, for benchmarks and the
exposure test of ``tests/test_regressions.py``.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

PERIOD = 140  # frames per exposure cycle


def auto_exposure_gain(i: int) -> float:
    """The gain of frame ``i``: per cycle of :data:`PERIOD` frames, 1.0 for frames 0-29, a 1.5x ramp over frames
    30-59 (a tunnel exit), held to frame 89, a sudden step to 0.7x at frame 90 and back to 1.0 at frame 120."""
    i = int(i) % PERIOD
    if i < 30:
        return 1.0
    if i < 60:
        return 1.0 + 0.5 * (i - 30) / 30
    return 1.5 if i < 90 else (0.7 if i < 120 else 1.0)


def exposure_copy(src: Path, dst: Path, brightness: float = 1.0) -> Path:
    """``dst``: the sequence folder ``src`` with frame ``i`` of ``rgb/`` (in name order) scaled by ``brightness x
    auto_exposure_gain(i)`` and clipped to 8 bits, as a camera would; every other entry of ``src`` is a symlink.
    Returns ``dst``.  An existing ``dst`` is an error (nothing is overwritten)."""
    import cv2

    src, dst = Path(src), Path(dst)
    names = sorted(p.name for p in (src / "rgb").iterdir()) if (src / "rgb").is_dir() else []
    if not names:
        raise FileNotFoundError(f"{src / 'rgb'}: no images to apply the exposure to")
    if dst.exists():
        raise FileExistsError(f"{dst} exists; exposure_copy writes a new folder")
    (dst / "rgb").mkdir(parents=True)
    for entry in src.iterdir():
        if entry.name != "rgb":
            os.symlink(entry.resolve(), dst / entry.name)
    for i, name in enumerate(names):
        img = cv2.imread(str(src / "rgb" / name), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{src / 'rgb' / name}: not a readable image")
        out = np.clip(img.astype(np.float32) * (brightness * auto_exposure_gain(i)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(dst / "rgb" / name), out)
    return dst
