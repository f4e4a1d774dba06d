"""The streaming API: frames fed one at a time give the same run as the batch pipeline on the same images."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from own_data import CX, CY, FPS, FX, H, N, W, own_data
from pvslam_core.api import Tracker, evaluate_run_dir, run_path
from pvslam_core.outputs.trajectory_io import read_tum
from pvslam_core.types import Intrinsics


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return own_data(tmp_path_factory)


@pytest.fixture(scope="module")
def images(data):
    return [cv2.imread(str(p)) for p in sorted((data / "frames").glob("*.png"))]  # BGR, as OpenCV gives them


def test_streaming_gives_the_batch_run(data, images, tmp_path):
    batch = run_path(data / "frames", overrides=[f"run.output_dir={json.dumps(str(tmp_path))}", "run.progress=false"])
    out = []
    with Tracker(intrinsics=[FX, FX, CX, CY], bgr=True, run_dir=tmp_path / "live",
                 overrides=["run.progress=false"]) as tracker:
        for i, img in enumerate(images):
            pose, result = tracker.track(img, i / FPS)  # the images reader's timestamps: index / fps
            assert pose.shape == (7,) and pose.dtype == torch.float64 and result.frame_index == i
            out.append((pose, result))
    res = tracker.result
    assert res.poses.shape == (N, 7)
    assert torch.equal(res.poses, batch.poses)  # same frames, same pipeline: the same final trajectory
    assert torch.equal(res.keyframe_indices, batch.keyframe_indices)
    # the pose returned for each frame is the estimate at that time (placeholders before initialisation)
    init = [r.initialized for _, r in out]
    assert not init[0] and init[-1]
    # (the final BA still moves the newest pose: about 5 % of this 30-frame, 0.25-unit path; a placeholder or a
    # stale pose would be off by the whole path)
    assert torch.allclose(out[-1][0], res.poses[-1], atol=0.1 * float(res.poses[:, :3].norm(dim=1).max()))
    # the run directory is complete and re-evaluates without a dataset
    run = tmp_path / "live"
    ts, poses = read_tum(run / "trajectory.txt")
    assert len(ts) == N and np.allclose(poses, res.poses.numpy(), atol=1e-6)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["dataset"] == {"plugin": "none"} and cfg["segmenter"] == {"plugin": "none"}
    metrics = evaluate_run_dir(run)
    assert "streaming API" in metrics["evaluation_sources"]["dataset"]


def test_inputs_are_checked(images):
    t = Tracker(intrinsics=Intrinsics(FX, FX, CX, CY, W, H), run_dir=None, overrides=["run.progress=false"])
    rgb = images[0][:, :, ::-1]
    with pytest.raises(ValueError, match="images must be uint8"):
        t.track(rgb.astype(np.float32), 0.0)
    t.track(torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))), 0.0)  # a [3, H, W] tensor
    with pytest.raises(ValueError, match=r"frame 1: timestamp 0.0 does not increase"):
        t.track(rgb, 0.0)
    with pytest.raises(ValueError, match=rf"frame 1: image is 80x60 but the first image was {W}x{H}"):
        t.track(np.ascontiguousarray(rgb[::2, ::2]), 1.0)
    gray = cv2.cvtColor(images[1], cv2.COLOR_BGR2GRAY)
    assert t.track(gray, None).result.frame_index == 1  # grey; no timestamp: the wall clock
    assert t.close().poses.shape == (2, 7)
    with pytest.raises(RuntimeError, match="closed"):
        t.track(rgb, 5.0)
    wrong = Tracker(intrinsics=Intrinsics(FX, FX, CX, CY, 640, 480))
    with pytest.raises(ValueError, match=rf"intrinsics are for 640x480 images but the first image is {W}x{H}"):
        wrong.track(rgb, 0.0)


def test_an_error_in_the_callers_loop_keeps_what_was_tracked(data, images, tmp_path):
    run = tmp_path / "stopped"
    with pytest.raises(KeyboardInterrupt):
        with Tracker(intrinsics=str(data / "orb.yaml"), bgr=True, run_dir=run,
                     overrides=["run.progress=false"]) as tracker:
            for i, img in enumerate(images[:12]):
                tracker.track(img, i / FPS)
            raise KeyboardInterrupt
    ts, _ = read_tum(run / "trajectory.txt")
    assert len(ts) == 12
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["partial"] is True and metrics["frames_written"] == 12
    assert tracker.result is None
