"""The ``video`` reader on small MJPG/AVI files written with cv2.VideoWriter."""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from pvslam_core.datasets.base import DatasetError
from pvslam_plugins.datasets.video.config import VideoConfig
from pvslam_plugins.datasets.video.reader import VideoReader

W, H, N, FPS = 64, 48, 9, 15.0


def write_video(path: Path, n: int = N, fps: float = FPS) -> Path:
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    assert wr.isOpened(), "opencv cannot write MJPG/AVI here"
    for i in range(n):
        img = np.zeros((H, W, 3), np.uint8)
        img[:, :, 2] = 20 * i  # red channel encodes the frame number
        img[:, :, 1] = 100
        wr.write(img)
    wr.release()
    return path


def red(frame) -> float:
    return float(frame.image[0].float().mean())


def test_frames_count_and_timestamps(tmp_path):
    v = write_video(tmp_path / "clip.avi")
    r = VideoReader(VideoConfig(path=str(v), calib=[50, 50, 31.5, 23.5], crop_multiple=1))
    info = r.info()
    assert info.num_frames == N and info.name == "video_clip" and not info.has_gt_pose
    assert (info.intrinsics.width, info.intrinsics.height) == (W, H)
    frames = list(r)
    assert [f.index for f in frames] == list(range(N))
    assert [f.timestamp for f in frames] == pytest.approx([i / FPS for i in range(N)])
    assert [round(red(f) / 20) for f in frames] == list(range(N))
    assert abs(float(frames[0].image[1].float().mean()) - 100) < 3


def test_stride_random_access_and_fps_timestamps(tmp_path):
    v = write_video(tmp_path / "clip.avi")
    (tmp_path / "calib.txt").write_text("50 50 31.5 23.5\n")  # found beside the video
    r = VideoReader(VideoConfig(path=str(v), start=1, stride=3, timestamps="fps", fps=30))
    assert len(r) == 3
    assert [round(red(f) / 20) for f in r] == [1, 4, 7]
    assert [round(red(r[i]) / 20) for i in (2, 0, 1, 1)] == [7, 1, 4, 4]  # backwards jumps re-open the file
    assert [f.timestamp for f in r] == pytest.approx([1 / 30, 4 / 30, 7 / 30])


def test_resize_and_crop(tmp_path):
    v = write_video(tmp_path / "clip.avi")
    r = VideoReader(VideoConfig(path=str(v), calib=[50, 50, 31.5, 23.5], resize=(36, 28), crop_multiple=8))
    f = r[0]
    k = r.info().intrinsics
    assert (f.width, f.height) == (k.width, k.height) == (32, 24)
    assert k.fx == pytest.approx(50 * 36 / 64) and k.cx == pytest.approx((31.5 + 0.5) * 36 / 64 - 0.5 - 2)


def test_container_frame_count_is_verified(tmp_path, monkeypatch, caplog):
    v = write_video(tmp_path / "clip.avi")
    real = cv2.VideoCapture

    class Lying:
        def __init__(self, *a):
            self.cap = real(*a)

        def get(self, prop):
            return 99.0 if prop == cv2.CAP_PROP_FRAME_COUNT else self.cap.get(prop)

        def __getattr__(self, name):
            return getattr(self.cap, name)

    monkeypatch.setattr(cv2, "VideoCapture", Lying)
    with caplog.at_level(logging.WARNING):
        r = VideoReader(VideoConfig(path=str(v), calib=[50, 50, 31.5, 23.5]))
    assert len(r) == N and "container says 99 frames, 9 could be decoded" in caplog.text


# ------------------------------------------------------------------------------------------------ errors ----
def test_calibration_is_required(tmp_path):
    v = write_video(tmp_path / "clip.avi")
    with pytest.raises(DatasetError, match=r"no calibration.*calib\.txt"):
        VideoReader(VideoConfig(path=str(v)))


def test_calibration_with_wrong_count_names_file_and_count(tmp_path):
    v = write_video(tmp_path / "clip.avi")
    (tmp_path / "cam.txt").write_text("50 50 31.5\n")
    with pytest.raises(DatasetError, match=r"cam\.txt.*found 3"):
        VideoReader(VideoConfig(path=str(v), calib=str(tmp_path / "cam.txt")))


def test_unreadable_video_names_the_file(tmp_path):
    bad = tmp_path / "broken.avi"
    bad.write_bytes(b"RIFF....AVI garbage" * 10)
    with pytest.raises(DatasetError, match=r"broken\.avi"):
        VideoReader(VideoConfig(path=str(bad), calib=[50, 50, 31.5, 23.5]))
    with pytest.raises(DatasetError, match=r"nope\.avi: video file not found"):
        VideoReader(VideoConfig(path=str(tmp_path / "nope.avi"), calib=[50, 50, 31.5, 23.5]))


def test_end_out_of_range_names_the_file(tmp_path):
    v = write_video(tmp_path / "clip.avi")
    r = VideoReader(VideoConfig(path=str(v), calib=[50, 50, 31.5, 23.5], end=10))
    with pytest.raises(DatasetError, match=r"clip\.avi: end=10 is out of range.*9 frames"):
        len(r)


def test_registered_through_the_hook(monkeypatch):
    import pvslam_plugins.datasets.video as plugin
    from pvslam_core.registry import build_registry

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    assert build_registry(extra_modules=(plugin,)).get("dataset", "video").config_model is VideoConfig
