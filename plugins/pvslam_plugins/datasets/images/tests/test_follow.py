"""``follow = true``: a folder that is still being written is read as images appear, until a timeout."""
from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from pvslam_core.datasets.base import DatasetError
from pvslam_plugins.datasets.images.config import ImagesConfig
from pvslam_plugins.datasets.images.reader import ImagesReader

W, H = 48, 32


def png(i: int) -> bytes:
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 2] = 10 * i  # red = 10 x frame number
    return cv2.imencode(".png", img)[1].tobytes()


def writer(folder: Path, start: int, n: int, gap: float, partial_at: int = -1) -> threading.Thread:
    """Write frames start..start+n-1, ``gap`` s apart; frame ``partial_at`` is first written half-way."""

    def run():
        for i in range(start, start + n):
            time.sleep(gap)
            data = png(i)
            p = folder / f"{i:04d}.png"
            if i == partial_at:
                p.write_bytes(data[: len(data) // 2])  # the reader sees a truncated file first
                time.sleep(0.15)
            tmp = folder / f".{i:04d}.tmp"
            tmp.write_bytes(data)
            tmp.replace(p)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_a_growing_folder_is_read_until_the_timeout(tmp_path):
    folder = tmp_path / "live"
    folder.mkdir()
    (folder / "0000.png").write_bytes(png(0))
    r = ImagesReader(ImagesConfig(path=str(folder), calib=[40, 40, 23.5, 15.5], crop_multiple=1, follow=True,
                                  wait_timeout=0.6, fps=10))
    info = r.info()
    assert info.num_frames is None and info.intrinsics.width == W
    with pytest.raises(TypeError, match="not known"):
        len(r)
    t = writer(folder, 1, 5, gap=0.08, partial_at=3)
    t0 = time.monotonic()
    frames = list(r)
    elapsed = time.monotonic() - t0
    t.join()
    assert [f.index for f in frames] == list(range(6))
    assert [round(float(f.image[0].float().mean()) / 10) for f in frames] == list(range(6))
    assert [f.timestamp for f in frames] == pytest.approx([i / 10 for i in range(6)])
    assert 0.6 < elapsed < 5.0  # waited for the writer, then for the timeout, not longer


def test_stride_and_start_apply_to_a_followed_folder(tmp_path):
    folder = tmp_path / "live"
    folder.mkdir()
    for i in range(7):
        (folder / f"{i:04d}.png").write_bytes(png(i))
    r = ImagesReader(ImagesConfig(path=str(folder), calib=[40, 40, 23.5, 15.5], crop_multiple=1, follow=True,
                                  wait_timeout=0.2, start=1, stride=2))
    assert [round(float(f.image[0].float().mean()) / 10) for f in r] == [1, 3, 5]


def test_waits_for_the_first_image_then_gives_up(tmp_path):
    folder = tmp_path / "empty"
    folder.mkdir()
    t0 = time.monotonic()
    with pytest.raises(DatasetError, match=r"no image appeared within wait_timeout=0.3"):
        ImagesReader(ImagesConfig(path=str(folder), calib=[40, 40, 23.5, 15.5], follow=True, wait_timeout=0.3))
    assert time.monotonic() - t0 >= 0.3
    writer(folder, 0, 1, gap=0.1).join()
    r = ImagesReader(ImagesConfig(path=str(folder), calib=[40, 40, 23.5, 15.5], follow=True, wait_timeout=0.3))
    assert r.info().intrinsics.height == H
