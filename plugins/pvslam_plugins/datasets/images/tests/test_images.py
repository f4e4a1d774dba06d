"""The ``images`` reader on folders written by the test."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pvslam_core.datasets.base import DatasetError
from pvslam_core.datasets.calib import read_calibration
from pvslam_plugins.datasets.images.config import ImagesConfig
from pvslam_plugins.datasets.images.reader import ImagesReader


def write_images(folder: Path, names: list[str], size=(48, 32), gray=False) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, n in enumerate(names):
        img = np.zeros((size[1], size[0], 3), np.uint8)
        img[..., 0], img[..., 1], img[..., 2] = 10 * i, 100, 200  # B, G, R
        if gray:
            img = img[..., 0]
        cv2.imwrite(str(folder / n), img)


def test_natural_order_fps_timestamps_and_rgb(tmp_path):
    names = ["f10.png", "f2.png", "f1.png", "f3.jpg"]
    write_images(tmp_path / "seq", names)
    (tmp_path / "seq" / "calib.txt").write_text("# fx fy cx cy\n40, 40, 23.5, 15.5\n")
    r = ImagesReader(ImagesConfig(path=str(tmp_path / "seq"), fps=5, crop_multiple=1))
    frames = list(r)
    assert [f.name for f in frames] == ["f1.png", "f2.png", "f3.jpg", "f10.png"]
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 0.2, 0.4, 0.6])
    f = frames[0]
    assert f.image.dtype == torch.uint8 and tuple(f.image.shape) == (3, 32, 48)
    assert f.image[:, 0, 0].tolist() == [200, 100, 20]  # R, G, B (f1 was written with B = 20)
    assert r.info().intrinsics.fx == 40 and not r.info().has_gt_pose


def test_grayscale_is_replicated(tmp_path):
    write_images(tmp_path, ["a.png"], gray=True)
    r = ImagesReader(ImagesConfig(path=str(tmp_path), calib=[40, 40, 23.5, 15.5]))
    img = r[0].image
    assert torch.equal(img[0], img[1]) and torch.equal(img[1], img[2])


def test_filename_timestamps_and_groundtruth(tmp_path):
    stamps = [1305031102.175304, 1305031102.211214, 1305031102.243211]
    write_images(tmp_path / "rgb", [f"{t:.6f}.png" for t in stamps])
    gt = tmp_path / "gt.txt"
    gt.write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        "1305031102.1758 1 2 3 0 0 0 1\n"
        "1305031102.2108 4 5 6 0 0 0 1\n"
    )
    r = ImagesReader(ImagesConfig(path=str(tmp_path / "rgb"), calib=[40, 40, 23.5, 15.5],
                                  timestamps="filename", groundtruth=str(gt)))
    frames = list(r)
    assert [f.timestamp for f in frames] == pytest.approx(stamps)
    assert frames[0].gt_pose[:3].tolist() == [1, 2, 3]
    assert frames[1].gt_pose[:3].tolist() == [4, 5, 6]
    assert frames[2].gt_pose is None  # 32 ms from the nearest ground truth
    assert r.info().has_gt_pose


def test_nanosecond_file_names(tmp_path):
    write_images(tmp_path, ["1403636579763555584.png", "1403636579813555456.png"])
    r = ImagesReader(ImagesConfig(path=str(tmp_path), calib=[40, 40, 23.5, 15.5], timestamps="filename"))
    assert [f.timestamp for f in r] == pytest.approx([1403636579.763555584, 1403636579.813555456])


def test_calibration_file_option_with_distortion(tmp_path):
    write_images(tmp_path / "imgs", ["0.png"])
    calib = tmp_path / "cam.txt"
    calib.write_text("40 41 23.5 15.5 -0.1 0.01 0.001 0.002 0.0003\n")
    r = ImagesReader(ImagesConfig(path=str(tmp_path / "imgs"), calib=str(calib), undistort=False, crop_multiple=1))
    k = r.info().intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (40, 41, 23.5, 15.5, 48, 32)
    assert k.dist == (-0.1, 0.01, 0.001, 0.002, 0.0003)
    assert read_calibration(calib, 48, 32) == k


# ------------------------------------------------------------------------------------------------ errors ----
def test_missing_calibration_says_where_it_looked(tmp_path):
    write_images(tmp_path / "imgs", ["0.png"])
    with pytest.raises(DatasetError, match=r"no calibration.*calib\.txt"):
        ImagesReader(ImagesConfig(path=str(tmp_path / "imgs")))


@pytest.mark.parametrize("text, count", [("40 40 23.5", 3), ("1 2 3 4 5 6", 6), ("1 2 3 4 5 6 7 8 9 10", 10)])
def test_calibration_with_wrong_count_names_file_and_count(tmp_path, text, count):
    write_images(tmp_path, ["0.png"])
    (tmp_path / "calib.txt").write_text(text + "\n")
    with pytest.raises(DatasetError, match=rf"calib\.txt.*found {count}"):
        ImagesReader(ImagesConfig(path=str(tmp_path)))


def test_calibration_values_with_wrong_count(tmp_path):
    write_images(tmp_path, ["0.png"])
    with pytest.raises(DatasetError, match="found 5"):
        ImagesReader(ImagesConfig(path=str(tmp_path), calib=[1, 2, 3, 4, 5]))


def test_corrupt_image_names_the_file(tmp_path):
    write_images(tmp_path, ["0.png", "1.png", "2.png"])
    (tmp_path / "1.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    r = ImagesReader(ImagesConfig(path=str(tmp_path), calib=[40, 40, 23.5, 15.5]))
    with pytest.raises(DatasetError, match=r"1\.png: unreadable or corrupt image"):
        list(r)


def test_unsorted_groundtruth_names_the_file(tmp_path):
    write_images(tmp_path / "imgs", ["0.png"])
    gt = tmp_path / "gt.txt"
    gt.write_text("0.2 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"gt\.txt.*unsorted"):
        ImagesReader(ImagesConfig(path=str(tmp_path / "imgs"), calib=[40, 40, 23.5, 15.5], groundtruth=str(gt)))
    gt.write_text("0.1 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"gt\.txt.*duplicate"):
        ImagesReader(ImagesConfig(path=str(tmp_path / "imgs"), calib=[40, 40, 23.5, 15.5], groundtruth=str(gt)))


def test_duplicate_filename_timestamps(tmp_path):
    write_images(tmp_path, ["1.0.png", "1.png"])
    with pytest.raises(DatasetError, match="duplicate timestamps"):
        ImagesReader(ImagesConfig(path=str(tmp_path), calib=[40, 40, 23.5, 15.5], timestamps="filename"))


def test_start_out_of_range_names_the_folder(tmp_path):
    write_images(tmp_path, ["0.png", "1.png"])
    r = ImagesReader(ImagesConfig(path=str(tmp_path), calib=[40, 40, 23.5, 15.5], start=2))
    with pytest.raises(DatasetError, match=rf"{tmp_path}.*start=2 is out of range.*2 frames"):
        len(r)


def test_empty_or_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match="no images"):
        ImagesReader(ImagesConfig(path=str(tmp_path), calib=[40, 40, 23.5, 15.5]))
    with pytest.raises(DatasetError, match="not found"):
        ImagesReader(ImagesConfig(path=str(tmp_path / "nope"), calib=[40, 40, 23.5, 15.5]))


def test_registered_through_the_hook(monkeypatch):
    import pvslam_plugins.datasets.images as plugin
    from pvslam_core.registry import build_registry

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    spec = build_registry(extra_modules=(plugin,)).get("dataset", "images")
    assert spec.config_model is ImagesConfig
