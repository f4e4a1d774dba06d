"""FlowFrontend.prefetch: the next frame's tracking flows begun on another thread are taken only by that frame with
the inputs they were begun with, and tracking gives bit for bit what it gives without them."""
from contextlib import contextmanager

import cv2
import numpy as np
import torch

from pvslam_core.types import Frame, Intrinsics
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend

K = Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)


def _frames(n: int, seed: int = 4) -> list[Frame]:
    """A textured plane panning 3 px a frame (so most frames track, some become keyframes)."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur((rng.random((120, 220)) * 255).astype(np.uint8), (0, 0), 2.0)
    out = []
    for i in range(n):
        g = np.ascontiguousarray(base[:, 3 * i:3 * i + 160])
        out.append(Frame(i, 0.1 * i, torch.from_numpy(np.stack([g, g, g])), K))
    return out


@contextmanager
def _frontend(threads: int = 2):
    fe = FlowFrontend(FlowFrontendConfig(dis={"threads": threads}), ba_downsample=8)
    try:
        yield fe
    finally:
        fe.pairs.close()


def _start(fe: FlowFrontend, frames: list[Frame]) -> None:
    """Frame 0 the first keyframe, frame 1 prefetched."""
    fe.track(frames[0], None)
    fe.add_keyframe(0, frames[0], None)
    fe.prefetch(frames[1])


def _drive(frames: list[Frame], prefetch: bool, keyframe_every: int = 4):
    """Track every frame (each ``keyframe_every``-th becomes a keyframe); with ``prefetch`` the next frame is
    handed over after each one, as the mapper does."""
    got = []
    with _frontend() as fe:
        for i, frame in enumerate(frames):
            r = fe.track(frame, None)
            got.append((r.is_keyframe, r.failed, None if r.target is None else r.target.clone(),
                        None if r.weight is None else r.weight.clone()))
            if i % keyframe_every == 0:
                fe.add_keyframe(i, frame, None)
            if prefetch and i + 1 < len(frames):
                fe.prefetch(frames[i + 1])
        return got, dict(fe.stats)


def test_tracking_with_the_next_frame_prefetched_is_bit_equal():
    frames = _frames(12)
    (plain, s0), (ahead, s1) = _drive(frames, False), _drive(frames, True)
    assert s0["track_prefetched"] == 0 and s1["track_prefetched"] == len(frames) - 1  # all but the first keyframe
    assert s0["dis_calls"] == s1["dis_calls"] > 0  # the prefetched calls are counted once, when taken
    assert s0["track_predicted_starts"] == s1["track_predicted_starts"]
    for (k0, f0, t0, w0), (k1, f1, t1, w1) in zip(plain, ahead):
        assert (k0, f0) == (k1, f1)
        assert (t0 is None) == (t1 is None) and (t0 is None or (torch.equal(t0, t1) and torch.equal(w0, w1)))


def test_a_prefetch_for_other_inputs_is_not_taken():
    frames = _frames(5)
    with _frontend() as fe:
        _start(fe, frames)
        fe.track(frames[2], None)  # another frame than the one prefetched
        assert fe.stats["track_prefetched"] == 0
        fe.prefetch(frames[3])
        fe.add_keyframe(2, frames[2], None)  # the reference changed after the prefetch
        fe.track(frames[3], None)
        assert fe.stats["track_prefetched"] == 0
        fe.prefetch(frames[4])  # the frame, the reference and the previous frame as the track will have them
        assert not fe.track(frames[4], None).failed
        assert fe.stats["track_prefetched"] == 1


def test_one_flow_thread_prefetches_nothing():
    frames = _frames(3)
    with _frontend(threads=1) as fe:
        _start(fe, frames)
        fe.track(frames[1], None)
        assert fe.stats["track_prefetched"] == 0
