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


def kitti_rows(fx: float = FX, cx: float = CX, cy: float = CY, baseline: float = 0.54) -> str:
    """KITTI odometry calib.txt text: P0..P3 (P1/P3 a stereo pair ``baseline`` m to the right), Tr."""
    rows = []
    for k, t in enumerate((0.0, -fx * baseline, 0.06 * fx, -fx * (baseline - 0.06))):
        rows.append(f"P{k}: " + " ".join(f"{v:.12e}" for v in (fx, 0, cx, t, 0, fx, cy, 0, 0, 0, 1, 0)))
    rows.append("Tr: " + " ".join(f"{v:.12e}" for v in (1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0)))
    return "\n".join(rows) + "\n"


EUROC_SENSOR = f"""sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
rate_hz: {FPS}
resolution: [{W}, {H}]
camera_model: pinhole
intrinsics: [{FX}, {FX}, {CX}, {CY}]
distortion_model: radial-tangential
distortion_coefficients: [0.0, 0.0, 0.0, 0.0]
"""


def own_layouts(tmp_path_factory) -> dict[str, Path]:
    """The own-data frames as the layouts users bring, each with its own calibration: a KITTI sequence folder under
    a parent not named ``sequences`` (calib.txt of P0..P3; times.txt with 5 rows more than images), an EuRoC
    sequence (mav0/cam0 + sensor.yaml), a TUM folder (rgb.txt; its calibration: ORB-SLAM's YAML, ``orb.yaml``)."""
    if "layouts" in _CACHE:
        return _CACHE["layouts"]
    root = own_data(tmp_path_factory)
    out = root / "layouts"
    frames = sorted((root / "frames").glob("*.png"))
    kitti = out / "drives" / "my_drive"
    (kitti / "image_0").mkdir(parents=True)
    (kitti / "calib.txt").write_text(kitti_rows())
    (kitti / "times.txt").write_text("".join(f"{i / FPS:.6e}\n" for i in range(len(frames) + 5)))
    cam0 = out / "euroc_mine" / "mav0" / "cam0"
    (cam0 / "data").mkdir(parents=True)
    (cam0 / "sensor.yaml").write_text(EUROC_SENSOR)
    tum = out / "tum_mine"
    (tum / "rgb").mkdir(parents=True)
    csv, rgb = ["#timestamp [ns],filename"], ["# timestamp filename"]
    for i, f in enumerate(frames):
        shutil.copy(f, kitti / "image_0" / f"{i:06d}.png")
        ns = 1403636579763555584 + i * int(1e9 / FPS)
        shutil.copy(f, cam0 / "data" / f"{ns}.png")
        csv.append(f"{ns},{ns}.png")
        t = 1305031102.175304 + i / FPS
        shutil.copy(f, tum / "rgb" / f"{t:.6f}.png")
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
    (cam0 / "data.csv").write_text("\n".join(csv) + "\n")
    (tum / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "kitti_calib.txt").write_text(kitti_rows())
    _CACHE["layouts"] = {"kitti": kitti, "euroc": out / "euroc_mine", "tum": tum, "video": root / "clip.avi",
                         "orb": root / "orb.yaml", "kitti_calib": root / "kitti_calib.txt"}
    return _CACHE["layouts"]
