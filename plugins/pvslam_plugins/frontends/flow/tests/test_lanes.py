"""lanes.py: independent DIS calls on two threads give exactly the flows of one thread, in any order."""
import cv2
import numpy as np
import pytest

from pvslam_plugins.frontends.flow import flow_ops as F
from pvslam_plugins.frontends.flow.lanes import DisLanes


def _images(n=4, seed=0):
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur((rng.random((120, 160)) * 255).astype(np.uint8), (0, 0), 2.0)
    return [np.ascontiguousarray(np.roll(base, 2 * k, axis=1)) for k in range(n)], rng


def _calls(imgs, rng):
    init = rng.normal(0, 2, (120, 160, 2)).astype(np.float32)
    calls = []
    for a in range(len(imgs)):
        for b in range(len(imgs)):
            if a != b:
                calls.append(("edge", imgs[a], imgs[b], None))
                calls.append(("edge_init", imgs[a], imgs[b], init))
                calls.append(("track", imgs[b], imgs[a], None))
    return calls


def test_two_threads_give_the_flows_of_one_in_any_order():
    imgs, rng = _images()
    calls = _calls(imgs, rng)
    make = lambda kind: F.create_dis("ultrafast", finest_scale=0)  # noqa: E731
    # the reference: a fresh DIS object per call (a function of the call's inputs alone)
    ref = [F.compute_flow(make(k), i0, i1, init) for k, i0, i1, init in calls]
    one, two = DisLanes(make, 1), DisLanes(make, 2)
    try:
        for lanes in (one, two):
            flows, seconds = lanes.run(calls)
            assert seconds > 0 and len(flows) == len(calls)
            for f, r in zip(flows, ref):
                np.testing.assert_array_equal(f, r)
            order = np.random.default_rng(1).permutation(len(calls))  # again, shuffled: no state carried over
            flows = lanes.run([calls[i] for i in order])[0]
            for f, i in zip(flows, order):
                np.testing.assert_array_equal(f, ref[i])
    finally:
        two.close()


def test_flows_do_not_depend_on_opencv_threads():
    """DIS splits its patch search into stripes by OpenCV's thread count (the machine's cores by default); its flows
    are still the same to the bit with 1, 2 or 4 threads, so a run does not depend on the machine's core count."""
    imgs, rng = _images()
    calls = _calls(imgs, rng)[:9]
    saved = cv2.getNumThreads()
    out = []
    try:
        for n in (1, 2, 4):
            cv2.setNumThreads(n)
            out.append([F.compute_flow(F.create_dis("ultrafast", finest_scale=0), i0, i1, init)
                        for _, i0, i1, init in calls])
    finally:
        cv2.setNumThreads(saved)
    for flows in out[1:]:
        for f, r in zip(flows, out[0]):
            np.testing.assert_array_equal(f, r)


def test_a_call_must_match_its_kind():
    lanes = DisLanes(lambda kind: F.create_dis("ultrafast"), 1)
    img = np.zeros((32, 32), np.uint8)
    with pytest.raises(ValueError, match="needs initial flow"):
        lanes.run([("edge_init", img, img, None)])
    with pytest.raises(ValueError, match="unknown DIS call kind"):
        lanes.run([("loop", img, img, None)])


def test_frontend_observations_do_not_depend_on_flow_threads():
    """A short synthetic drive through the whole frontend (tracking, keyframes, edges with reprojection inits):
    bit-equal targets and weights with 1 and 2 threads."""
    import torch

    from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
    from pvslam_plugins.frontends.flow.frontend import FlowFrontend
    from pvslam_core.types import Frame, Intrinsics

    imgs, _ = _images(6, seed=3)
    k = Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)
    out = []
    for threads in (1, 2):
        fe = FlowFrontend(FlowFrontendConfig(dis={"threads": threads}), ba_downsample=8)
        tracks = []
        for i, g in enumerate(imgs):
            frame = Frame(i, 0.1 * i, torch.from_numpy(np.stack([g, g, g])), k)
            r = fe.track(frame, None)
            tracks.append((r.is_keyframe, None if r.target is None else r.target.clone()))
            fe.add_keyframe(i, frame, None)
        out.append((tracks, dict(fe.stats)))
        fe.pairs.close()
    (t1, s1), (t2, s2) = out
    assert s1["dis_calls"] == s2["dis_calls"] > 0
    for (k1, a), (k2, b) in zip(t1, t2):
        assert k1 == k2
        assert (a is None) == (b is None) and (a is None or torch.equal(a, b))


def test_a_run_is_bit_equal_with_one_and_two_flow_threads(tmp_path):
    """The whole pipeline (edges with reprojection inits, dynamic masks, BA): the same trajectory to the bit."""
    from pvslam_core.api import run_config

    poses = []
    for threads in (1, 2):
        r = run_config(None, overrides=[
            'dataset.scenario="driving_loop"', "dataset.num_frames=40", f"frontend.dis.threads={threads}",
            f'run.output_dir="{(tmp_path / str(threads)).as_posix()}"', "run.progress=false",
            "evaluation.enabled=false", "outputs.ply=false", "outputs.plots=false", "outputs.panoptic_png=false"])
        poses.append(r.poses)
    assert poses[0].shape[0] == 40
    assert np.array_equal(np.asarray(poses[0]), np.asarray(poses[1]))


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")
def test_a_forked_child_gets_its_own_workers():
    """A child forked after the pool started inherits the pool object but not its threads: it must not wait on
    workers that do not exist (it starts its own)."""
    import os
    import warnings

    imgs, rng = _images()
    calls = _calls(imgs, rng)[:6]
    lanes = DisLanes(lambda kind: F.create_dis("ultrafast", finest_scale=0), 2)
    ref = lanes.run(calls)[0]  # the parent's worker thread exists now
    r, w = os.pipe()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # Python 3.12+: fork with threads running
        pid = os.fork()
    if pid == 0:  # the child: compute, report, leave without running the parent's cleanup
        import signal

        signal.alarm(30)  # a child waiting on the parent's (absent) workers is killed: the test fails, not hangs
        try:
            ok = all(np.array_equal(a, b) for a, b in zip(lanes.run(calls)[0], ref))
            os.write(w, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.close(w)
    try:
        _, status = os.waitpid(pid, 0)
        assert os.read(r, 1) == b"1" and status == 0
    finally:
        os.close(r)
        lanes.close()


def test_the_caller_does_not_wait_for_a_busy_worker():
    """map's items go to whichever thread is free: while the only worker is held by an earlier submit, the caller
    computes every item itself and returns, in order, without waiting for the worker."""
    import threading

    lanes = DisLanes(lambda kind: F.create_dis("ultrafast"), 2)
    release = threading.Event()
    try:
        held = lanes.submit(release.wait, 30)
        assert lanes.map(lambda x: 2 * x, [1, 2, 3, 4]) == [2, 4, 6, 8]
        assert not held.done()  # the worker is still held: nothing above waited for it
        release.set()
        assert held.result(timeout=30) is True
        calls = _calls(*_images(3))[:5]
        assert all(np.array_equal(a, b) for a, b in zip(lanes.run(calls)[0], DisLanes(lanes._make, 1).run(calls)[0]))
    finally:
        release.set()
        lanes.close()


def test_an_error_in_an_item_reaches_the_caller():
    lanes = DisLanes(lambda kind: F.create_dis("ultrafast"), 2)

    def fn(x):
        if x == 3:
            raise RuntimeError("item 3")
        return x

    try:
        with pytest.raises(RuntimeError, match="item 3"):
            lanes.map(fn, [1, 2, 3, 4, 5])
        assert lanes.map(fn, [1, 2]) == [1, 2]  # the lanes still work afterwards
    finally:
        lanes.close()
