"""Per-frame files are renamed into place without an fsync each; the run's own record is fsynced first."""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from pvslam_core.outputs import _atomic
from pvslam_core.outputs.panoptic_png import load_panoptic, save_panoptic
from pvslam_core.outputs.trajectory_io import write_tum
from pvslam_core.types import PanopticSegmentation, Segment


@pytest.fixture()
def fsyncs(monkeypatch):
    calls: list[int] = []
    real = os.fsync

    def counting(fd):
        calls.append(fd)
        real(fd)

    monkeypatch.setattr(_atomic.os, "fsync", counting)
    return calls


def test_a_panoptic_png_is_written_whole_without_an_fsync(tmp_path, fsyncs):
    ids = np.ones((6, 9), np.int64)
    ids[2:4, 3:6] = 70_001
    seg = PanopticSegmentation(torch.from_numpy(ids), [Segment(1, 1, False), Segment(70_001, 2, True)])
    path = tmp_path / "panoptic" / "000000.png"
    info = save_panoptic(path, seg)
    assert fsyncs == []
    assert np.array_equal(load_panoptic(path, info).ids.numpy(), ids)
    assert [p.name for p in path.parent.iterdir()] == ["000000.png"]  # no temporary file left behind


def test_a_trajectory_is_fsynced_before_it_replaces_the_old_one(tmp_path, fsyncs):
    poses = np.tile(np.array([0, 0, 0, 0, 0, 0, 1.0]), (3, 1))
    write_tum(tmp_path / "trajectory.txt", np.arange(3.0), poses)
    assert len(fsyncs) == 1
    rows = [r for r in (tmp_path / "trajectory.txt").read_text().splitlines() if not r.startswith("#")]
    assert len(rows) == 3


def test_a_failed_per_frame_write_keeps_the_old_file(tmp_path, fsyncs):
    path = tmp_path / "f.bin"
    _atomic.atomic_write_bytes(path, b"old", durable=False)
    with pytest.raises(RuntimeError):
        with _atomic.atomic_open(path, "wb", durable=False) as f:
            f.write(b"half")
            raise RuntimeError("stopped mid-write")
    assert path.read_bytes() == b"old" and fsyncs == []
