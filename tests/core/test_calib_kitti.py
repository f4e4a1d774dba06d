"""KITTI's own calibration files (odometry calib.txt: P0..P3 rows; raw calib_cam_to_cam.txt: P_rect_0N rows) are
read wherever a calibration file is (--calib, a reader's calib.txt), taking the row of the camera in use and
saying which."""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from pvslam_core.cli import main
from pvslam_core.datasets.base import DatasetError
from pvslam_core.datasets.calib import calibration_from_option, read_calibration
from pvslam_core.datasets.detect import dataset_section
from pvslam_core.registry import get_registry


def row(name: str, fx: float, cx: float = 600.5, cy: float = 180.5, t: float = 0.0) -> str:
    return f"{name}: " + " ".join(f"{v:.12e}" for v in (fx, 0, cx, t, 0, fx, cy, 0, 0, 0, 1, 0))


#: odometry calib.txt: camera k has fx = 700 + k, so the row taken shows in the intrinsics
ODOMETRY = "\n".join([row(f"P{k}", 700.0 + k, t=-386.1 * (k % 2)) for k in range(4)]
                     + ["Tr: " + " ".join(["1", "0", "0", "0"] * 3)]) + "\n"
#: raw calib_cam_to_cam.txt: lines of other shapes (a date, 2, 3, 5 and 9 values) around the P_rect rows
RAW = "calib_time: 09-Jan-2012 13:57:47\ncorner_dist: 9.950000e-02\n" + "".join(
    f"S_0{k}: 1.392000e+03 5.120000e+02\nK_0{k}: 9.842439e+02 0 6.9e+02 0 9.808141e+02 2.331966e+02 0 0 1\n"
    f"D_0{k}: -3.728755e-01 2.037299e-01 2.219027e-03 1.383707e-03 -7.233722e-02\nT_0{k}: 0 0 0\n"
    f"S_rect_0{k}: 1.242000e+03 3.750000e+02\n{row(f'P_rect_0{k}', 720.0 + k, 609.5, 172.8)}\n" for k in range(4))


def png(path: Path, w: int = 1241, h: int = 376) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((h, w), 90, np.uint8))


def test_odometry_calib_txt_gives_the_row_of_the_camera_and_says_which(tmp_path, caplog):
    p = tmp_path / "calib.txt"
    p.write_text(ODOMETRY)
    with caplog.at_level(logging.INFO, logger="pvslam.notice"):
        k = read_calibration(p, 1241, 376)
        k2 = read_calibration(p, 1241, 376, camera=2)
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height, k.dist) == (700.0, 700.0, 600.5, 180.5, 1241, 376, ())
    assert k2.fx == 702.0
    assert f"{p}: KITTI projection row P0 (the default camera)" in caplog.text
    assert "KITTI projection row P2 (camera image_2, from the image folder's name)" in caplog.text
    assert calibration_from_option(str(p), 1241, 376, camera=1).fx == 701.0  # what --calib and readers use


def test_raw_cam_to_cam_gives_the_rectified_row(tmp_path):
    p = tmp_path / "calib_cam_to_cam.txt"
    p.write_text(RAW)
    assert read_calibration(p, 1242, 375).fx == 720.0
    k = read_calibration(p, 1242, 375, camera=2)
    assert (k.fx, k.cx, k.cy) == (722.0, 609.5, 172.8)


def test_the_image_folder_reader_takes_the_row_its_folder_names(tmp_path, caplog):
    """A plain image folder: P0 by default, P2 in a folder named image_2; KITTI raw's image_02/data takes
    P_rect_02 of calib_cam_to_cam.txt given with --calib."""
    reg = get_registry()

    def intrinsics(path, calib=None):
        det = dataset_section(path, calib)
        assert det.plugin == "images", det
        spec = reg.get("dataset", "images")
        return spec.factory(spec.config_model(**det.options, crop_multiple=1, max_pixels=None), None).info().intrinsics

    png(tmp_path / "frames" / "0.png")
    (tmp_path / "frames" / "calib.txt").write_text(ODOMETRY)
    assert intrinsics(tmp_path / "frames").fx == 700.0
    png(tmp_path / "cam" / "image_2" / "0000000000.png")  # no 000000.png beside a calib.txt: not a KITTI sequence
    (tmp_path / "cam" / "image_2" / "calib.txt").write_text(ODOMETRY)
    assert intrinsics(tmp_path / "cam" / "image_2").fx == 702.0
    drive = tmp_path / "2011_09_26" / "2011_09_26_drive_0001_sync" / "image_02" / "data"
    png(drive / "0000000000.png", 1242, 375)
    (tmp_path / "2011_09_26" / "calib_cam_to_cam.txt").write_text(RAW)
    assert intrinsics(drive, tmp_path / "2011_09_26" / "calib_cam_to_cam.txt").fx == 722.0


def test_a_missing_row_and_a_short_row_are_named(tmp_path):
    p = tmp_path / "calib.txt"
    p.write_text("\n".join(ODOMETRY.splitlines()[:2]) + "\n")  # P0, P1 only
    with pytest.raises(DatasetError, match=r"calib\.txt: no P3 or P_rect_03 row for camera image_3 \(the file has: "
                                           r"P0, P1\)"):
        read_calibration(p, 1241, 376, camera=3)
    p.write_text(ODOMETRY.replace(" 1.000000000000e+00 0.000000000000e+00\n", " 1.000000000000e+00\n", 1))
    with pytest.raises(DatasetError, match=r"calib\.txt:1: P0 needs 12 values \(3x4 matrix\), found 11"):
        read_calibration(p, 1241, 376)


def test_cli_runs_an_image_folder_with_kitti_calib_txt(tmp_path, capsys):
    """`pvslam run frames/ --calib calib.txt` with KITTI's file: the run starts (the frames are blank, so it
    estimates no motion: exit status 3, not a calibration error)."""
    for i in range(3):
        png(tmp_path / "frames" / f"f{i}.png", 64, 48)
    (tmp_path / "calib.txt").write_text("\n".join(row(f"P{k}", 60.0, 31.5, 23.5) for k in range(4)) + "\n")
    code = main(["run", str(tmp_path / "frames"), "--calib", str(tmp_path / "calib.txt"), "--output-dir",
                 str(tmp_path / "runs"), "-q", "--set", "loop.plugin=none"])
    err = capsys.readouterr().err
    assert code in (0, 3), err
    assert "KITTI projection row P0 (the default camera)" in err and "parseValue" not in err
