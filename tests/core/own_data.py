"""A user's own data for the tests: a short synthetic drive (enough parallax to initialise) written as a plain
image folder and as an MJPG video, with the calibration in the formats users bring.  Generated once per process."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2

W, H, N, FPS = 160, 120, 30, 10.0
FX, CX, CY = 136.0, 79.5, 59.5  # the synthetic camera: 0.85 W, centred

ORB_SLAM2_YAML = f"""%YAML:1.0
Camera.fx: {FX}
Camera.fy: {FX}
Camera.cx: {CX}
Camera.cy: {CY}
Camera.k1: 0.0
Camera.k2: 0.0
Camera.p1: 0.0
Camera.p2: 0.0
Camera.width: {W}
Camera.height: {H}
"""

_CACHE: dict[str, Path] = {}


def own_data(tmp_path_factory) -> Path:
    """``root/frames/000000.png...`` (+ ``calib.txt`` in DROID-SLAM's format), ``root/clip.avi``,
    ``root/orb.yaml`` (ORB-SLAM2), ``root/synthetic`` (the source, with labels and ground truth)."""
    if "root" in _CACHE:
        return _CACHE["root"]
    from pvslam_plugins.datasets.synthetic.generator import generate

    root = tmp_path_factory.mktemp("own_data")
    syn = generate("driving_loop", root / "synthetic", num_frames=N, width=W, height=H, progress=False)
    frames = root / "frames"
    frames.mkdir()
    wr = cv2.VideoWriter(str(root / "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    for i, f in enumerate(sorted((Path(syn) / "rgb").glob("*.png"))):
        shutil.copy(f, frames / f"{i:06d}.png")
        wr.write(cv2.imread(str(f)))
    wr.release()
    (frames / "calib.txt").write_text(f"{FX} {FX} {CX} {CY}\n")
    (root / "orb.yaml").write_text(ORB_SLAM2_YAML)
    _CACHE["root"] = root
    return root
