"""The pipeline's observer (what a live viewer implements): called for every frame, keyframe, loop and at the end;
one that raises is switched off and the run goes on."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from pvslam_core.api import run_config
from pvslam_core.observer import KeyframeSnapshot, RunObserver
from pvslam_core.slam import loops

LOOPS = ['loop.plugin="every_kf"', "dataset.frames=16"]


@pytest.fixture(autouse=True)
def _no_loop_suppression(monkeypatch):
    monkeypatch.setattr(loops, "NMS_KEYFRAMES", 0)  # every keyframe closes a loop


class Recorder(RunObserver):
    def __init__(self):
        self.calls: list[str] = []
        self.frames = []
        self.snaps: list[KeyframeSnapshot] = []
        self.loops = []

    def on_start(self, info, categories):
        self.calls.append("start")
        self.info, self.categories = info, list(categories)

    def on_frame(self, frame, result, panoptic):
        self.calls.append("frame")
        self.frames.append((frame.index, result.pose.clone(), result.is_keyframe, result.initialized,
                            panoptic is not None))

    def on_keyframes(self, keyframes):
        self.calls.append("keyframes")
        self.snaps.append(keyframes)

    def on_loop(self, loop, keyframes):
        self.calls.append("loop")
        self.loops.append(loop)

    def on_finish(self, result, keyframes):
        self.calls.append("finish")
        self.final = (result, keyframes)


def test_the_observer_sees_every_frame_keyframe_and_loop(fake_registry, fake_config_file):
    rec = Recorder()
    res = run_config(fake_config_file, overrides=LOOPS, registry=fake_registry, observer=rec)
    assert rec.calls[0] == "start" and rec.calls[-1] == "finish" and rec.calls.count("finish") == 1
    assert [f[0] for f in rec.frames] == list(range(16)) and all(f[4] for f in rec.frames)  # with panoptic
    kf_frames = [f for f in rec.frames if f[2] and f[3]]
    assert rec.calls.count("keyframes") == len(kf_frames) > 0  # after each keyframe once initialised
    assert [(lp.kf_i, lp.kf_j) for lp in rec.loops] == [(lp.kf_i, lp.kf_j) for lp in res.loops] and res.loops
    result, snap = rec.final
    assert result is res and torch.equal(snap.poses, res.keyframe_poses)
    assert snap.disps.shape[0] == snap.ids.shape[0] == len(res.keyframe_indices)
    assert set(snap.images) >= set(snap.ids.tolist())
    # each loop is reported after the frame that closed it, with the map of that moment
    assert rec.calls.index("loop") > rec.calls.index("keyframes")


class Broken(Recorder):
    def on_keyframes(self, keyframes):
        raise RuntimeError("viewer died")


def test_a_failing_observer_does_not_end_the_run(fake_registry, fake_config_file):
    rec = Broken()
    res = run_config(fake_config_file, overrides=LOOPS, registry=fake_registry, observer=rec)
    assert res.poses.shape == (16, 7)
    assert "finish" not in rec.calls and rec.calls.count("frame") < 16  # switched off at the first keyframe call
    log = (Path(res.run_dir) / "log.txt").read_text()
    assert "viewer switched off: its on_keyframes raised RuntimeError: viewer died" in log
