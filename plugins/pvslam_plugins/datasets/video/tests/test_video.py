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
        img[:, :, 2] = 20 * (i % 13)  # red channel encodes the frame number (mod 13)
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


class Counting:
    """cv2.VideoCapture wrapper that counts decode calls and can lie about the frame count."""

    real = cv2.VideoCapture
    grabs = 0
    claim: float | None = None

    def __init__(self, *a):
        self.cap = Counting.real(*a)

    def get(self, prop):
        if prop == cv2.CAP_PROP_FRAME_COUNT and Counting.claim is not None:
            return Counting.claim
        return self.cap.get(prop)

    def grab(self):
        Counting.grabs += 1
        return self.cap.grab()

    def read(self):
        Counting.grabs += 1
        return self.cap.read()

    def __getattr__(self, name):
        return getattr(self.cap, name)


@pytest.fixture
def counting(monkeypatch):
    monkeypatch.setattr(Counting, "grabs", 0)
    monkeypatch.setattr(Counting, "claim", None)
    monkeypatch.setattr(cv2, "VideoCapture", Counting)
    return Counting


def test_building_the_reader_decodes_nothing(tmp_path, counting):
    v = write_video(tmp_path / "clip.avi", n=40)
    r = VideoReader(VideoConfig(path=str(v), calib=[50, 50, 31.5, 23.5]))
    assert r.info().num_frames == 40 and counting.grabs == 0  # the container's count, no pass over the file
    assert [round(red(f) / 20) % 13 for f in r][:3] == [0, 1, 2] and counting.grabs == 41  # + the end-of-file grab


@pytest.mark.parametrize("claim", [99.0, 4.0])
def test_a_wrong_container_count_ends_gracefully(tmp_path, counting, caplog, claim):
    v = write_video(tmp_path / "clip.avi")
    counting.claim = claim
    r = VideoReader(VideoConfig(path=str(v), calib=[50, 50, 31.5, 23.5]))
    assert r.info().num_frames == int(claim)  # the claim, until the video is read
    with caplog.at_level(logging.WARNING):
        frames = list(r)
    assert [round(red(f) / 20) for f in frames] == list(range(N))  # every decodable frame, no error
    assert f"the container claims {int(claim)} frames, {N} were decoded" in caplog.text


def test_unknown_container_count_is_an_unknown_length(tmp_path, counting):
    v = write_video(tmp_path / "clip.avi")
    counting.claim = 0.0
    r = VideoReader(VideoConfig(path=str(v), calib=[50, 50, 31.5, 23.5], stride=2))
    assert r.info().num_frames is None
    with pytest.raises(TypeError, match="not known"):
        len(r)
    assert [f.index for f in r] == [0, 1, 2, 3, 4]
    assert [round(red(f) / 20) for f in r] == [0, 2, 4, 6, 8]


def test_truncated_file_ends_where_decoding_stops(tmp_path, caplog):
    v = write_video(tmp_path / "clip.avi", n=30)
    data = v.read_bytes()
    v.write_bytes(data[: len(data) * 2 // 3])  # the header still claims 30 frames; the index is gone
    r = VideoReader(VideoConfig(path=str(v), calib=[50, 50, 31.5, 23.5]))
    with caplog.at_level(logging.WARNING):
        frames = list(r)
    assert 5 < len(frames) < 30
    assert [round(red(f) / 20) % 13 for f in frames] == [i % 13 for i in range(len(frames))]
    assert r.info().num_frames == 30  # the header's claim
    assert f"the container claims 30 frames, {len(frames)} were decoded" in caplog.text


class FakeCamera:
    """What cv2.VideoCapture(0) gives: no frame count, a size, frames until the device stops."""

    def __init__(self, index, frames=7):
        assert isinstance(index, int)
        self.left = frames
        self.i = 0

    def isOpened(self):
        return True

    def get(self, prop):
        return {cv2.CAP_PROP_FRAME_WIDTH: W, cv2.CAP_PROP_FRAME_HEIGHT: H, cv2.CAP_PROP_FPS: 30.0}.get(prop, 0.0)

    def read(self):
        if self.left == 0:
            return False, None
        self.left -= 1
        img = np.zeros((H, W, 3), np.uint8)
        img[:, :, 2] = 20 * self.i
        self.i += 1
        return True, img

    def release(self):
        self.left = 0


def test_camera_index_is_a_live_source_of_unknown_length(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no file named "0" here
    monkeypatch.setattr(cv2, "VideoCapture", FakeCamera)
    r = VideoReader(VideoConfig(path="0", calib=[50, 50, 31.5, 23.5], crop_multiple=1))
    info = r.info()
    assert info.num_frames is None and info.name == "camera_0" and info.intrinsics.width == W
    frames = list(r)
    assert [round(red(f) / 20) for f in frames] == list(range(7))
    ts = [f.timestamp for f in frames]
    assert ts[0] == 0.0 and all(b > a for a, b in zip(ts, ts[1:]))  # wall clock since the first frame
    with pytest.raises(DatasetError, match="no random access"):
        r._load(0)


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
