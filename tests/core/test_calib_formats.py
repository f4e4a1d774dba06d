"""Calibration files a user brings: DROID-SLAM's values (up to 12), ORB-SLAM2/3 and OpenCV YAML/XML (read with
cv2.FileStorage), and a clear error otherwise."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from pvslam_core.datasets.base import DatasetError
from pvslam_core.datasets.calib import calibration_from_option, read_calibration

ORB2 = """%YAML:1.0

# Camera Parameters. Adjust them!
Camera.fx: 517.306408
Camera.fy: 516.469215
Camera.cx: 318.643040
Camera.cy: 255.313989

Camera.k1: 0.262383
Camera.k2: -0.953104
Camera.p1: -0.005358
Camera.p2: 0.002628
Camera.k3: 1.163314

Camera.width: 640
Camera.height: 480
Camera.fps: 30.0
Camera.RGB: 1
"""

ORB3 = """%YAML:1.0
File.version: "1.0"
Camera.type: "PinHole"
Camera1.fx: 458.654
Camera1.fy: 457.296
Camera1.cx: 367.215
Camera1.cy: 248.375
Camera1.k1: -0.28340811
Camera1.k2: 0.07395907
Camera1.p1: 0.00019359
Camera1.p2: 1.76187114e-05
Camera.width: 752
Camera.height: 480
"""

ROS = """image_width: 1280
image_height: 960
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [1000.0, 0.0, 639.5, 0.0, 1002.0, 479.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.1, -0.2, 0.001, 0.002, 0.0]
"""


def test_droid_slam_values_up_to_twelve(tmp_path):
    p = tmp_path / "calib.txt"
    p.write_text("500 501 319.5 239.5 0.1 0.01 0.001 0.002 0.003 0.01 0.001 0.0001\n")  # rational model
    k = read_calibration(p, 640, 480)
    assert (k.fx, k.fy, k.cx, k.cy) == (500, 501, 319.5, 239.5)
    assert k.dist == (0.1, 0.01, 0.001, 0.002, 0.003, 0.01, 0.001, 0.0001)
    # the same 8 coefficients are what cv2.undistort takes (DROID-SLAM's demo passes calib[4:] to it)
    img = np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8)
    cv2.undistort(img, k.matrix().numpy(), np.asarray(k.dist))
    for n in (4, 8, 9):
        p.write_text(" ".join(["500", "500", "31.5", "23.5", "0.01", "0.0", "0.0", "0.0", "0.0"][:n]))
        assert len(read_calibration(p, 64, 48).dist) == n - 4


@pytest.mark.parametrize("count", [5, 10, 11, 13])
def test_other_value_counts_are_refused_with_the_count(tmp_path, count):
    p = tmp_path / "calib.txt"
    p.write_text(" ".join(["500", "500", "319.5", "239.5"] + ["0.0"] * (count - 4)))
    with pytest.raises(DatasetError, match=rf"calib\.txt: expected 4, 8, 9 or 12 calibration values.*found {count}"):
        read_calibration(p, 640, 480)


def test_orb_slam2_yaml(tmp_path):
    p = tmp_path / "TUM1.yaml"
    p.write_text(ORB2)
    k = read_calibration(p, 640, 480)
    assert (k.fx, k.fy, k.cx, k.cy) == (517.306408, 516.469215, 318.643040, 255.313989)
    assert k.dist == (0.262383, -0.953104, -0.005358, 0.002628, 1.163314)
    # pySLAM-style files without the %YAML header, under another extension, read the same
    q = tmp_path / "settings.txt"
    q.write_text(ORB2.split("\n", 1)[1])
    assert read_calibration(q, 640, 480) == k


def test_orb_slam3_yaml_and_resolution_scaling(tmp_path):
    p = tmp_path / "EuRoC.yaml"
    p.write_text(ORB3)
    k = read_calibration(p, 752, 480)
    assert (k.fx, k.cx) == (458.654, 367.215) and k.dist == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    # the same sensor at half resolution: intrinsics scaled (pixel centres at integers), distortion unchanged
    h = read_calibration(p, 376, 240)
    assert h.fx == pytest.approx(458.654 / 2) and h.cx == pytest.approx((367.215 + 0.5) / 2 - 0.5)
    assert h.dist == k.dist and (h.width, h.height) == (376, 240)
    with pytest.raises(DatasetError, match=r"EuRoC\.yaml: the calibration is for 752x480 images but the images are "
                                           r"640x480"):
        read_calibration(p, 640, 480)


def test_fisheye_orb_slam3_model_is_refused(tmp_path):
    p = tmp_path / "fisheye.yaml"
    p.write_text(ORB3.replace('"PinHole"', '"KannalaBrandt8"'))
    with pytest.raises(DatasetError, match=r"fisheye\.yaml: Camera.type 'KannalaBrandt8' is not supported"):
        read_calibration(p, 752, 480)


def test_opencv_filestorage_written_by_opencv_itself(tmp_path):
    K = np.array([[500.0, 0, 319.5], [0, 501.0, 239.5], [0, 0, 1]])
    D = np.array([[0.1, -0.2, 0.001, 0.002, 0.05]])
    for name in ("cam.yml", "cam.xml"):
        p = tmp_path / name
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", 640)
        fs.write("image_height", 480)
        fs.write("camera_matrix", K)
        fs.write("distortion_coefficients", D)
        fs.release()
        k = read_calibration(p, 640, 480)
        assert (k.fx, k.fy, k.cx, k.cy) == (500.0, 501.0, 319.5, 239.5), name
        assert k.dist == pytest.approx(tuple(D.ravel())), name


def test_ros_camera_info_yaml(tmp_path):
    p = tmp_path / "ost.yaml"
    p.write_text(ROS)
    k = read_calibration(p, 640, 480)  # calibrated at 1280x960: scaled by one half
    assert k.fx == pytest.approx(500.0) and k.fy == pytest.approx(501.0) and k.cx == pytest.approx(319.5)
    assert k.dist == (0.1, -0.2, 0.001, 0.002, 0.0)


@pytest.mark.parametrize("name, text, needle", [
    ("notes.txt", "hello world\n", "not a number: 'hello'; expected one line 'fx fy cx cy"),
    ("empty.txt", "# nothing here\n", "no calibration values; expected one line"),
    ("other.yaml", "%YAML:1.0\nfoo: 1\nbar: 2\n", "no camera intrinsics found: expected Camera.fx"),
    ("broken.yaml", "camera_matrix: [1, 2\n  : bad", "not a readable YAML/XML calibration"),
    ("partial.yaml", "Camera.fx: 500\nCamera.fy: 500\nCamera.cx: 320\n", "missing Camera.cy"),
    ("halfdist.yaml", ORB2.replace("Camera.p2: 0.002628\n", ""), "incomplete distortion: missing Camera.p2"),
    ("badmat.yaml", "camera_matrix: [1, 2, 3, 4]\n", "camera_matrix must be a 3x3 matrix, found 4 values"),
    ("nan.yaml", ORB2.replace("517.306408", ".nan"), "Camera.fx=nan is not a finite number"),
    ("badfx.yaml", ORB2.replace("Camera.cy: 255.313989", "Camera.cy: 9000"), "cy=9000.0 lies far outside"),
    ("binary.txt", None, "not a text file; expected one line"),
])
def test_unreadable_calibrations_name_the_file_and_what_was_expected(tmp_path, name, text, needle):
    p = tmp_path / name
    if text is None:
        p.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    else:
        p.write_text(text)
    with pytest.raises(DatasetError) as err:
        read_calibration(p, 640, 480)
    msg = str(err.value)
    assert msg.startswith(str(p)) and needle in msg, msg


def test_calib_option_takes_a_yaml_file(tmp_path):
    p = tmp_path / "TUM1.yaml"
    p.write_text(ORB2)
    assert calibration_from_option(str(p), 640, 480).fx == 517.306408
    with pytest.raises(DatasetError, match="calibration file not found"):
        calibration_from_option(str(tmp_path / "nope.yaml"), 640, 480)
