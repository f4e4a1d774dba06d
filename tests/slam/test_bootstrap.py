"""Map initialisation on a sliding window of keyframe pairs (pvslam_core/slam/bootstrap.py), with the exact fake
plugins of the framework tests."""
import logging

import pytest
import torch

import fakes
from pvslam_core.config import validate_pipeline
from pvslam_core.geometry.testing import umeyama_ate
from pvslam_core.interfaces import BuildContext
from pvslam_core.registry import get_registry
from pvslam_core.slam import bootstrap as B
from pvslam_core.slam import loops
from pvslam_core.slam.mapper import Mapper
from pvslam_core.slam.observe import EdgeObserver


def test_init_pairs_slide_with_the_newest_keyframe():
    """Brute-force reference: every pair is distinct, ``first <= a < m <= k``, the first view is at most
    ``window`` keyframes back, the farthest pair comes first, and never more than ``tries``."""
    for first in (0, 3):
        for k in range(first + 1, first + 20):
            for window in (1, 2, 8):
                for tries in (1, 2, 3, 4):
                    pairs = B.init_pairs(first, k, window, tries)
                    assert 1 <= len(pairs) <= tries
                    assert len(set(pairs)) == len(pairs)
                    a0 = max(first, k - window)
                    assert pairs[0] == (a0, k)  # the most parallax first
                    for a, m in pairs:
                        assert first <= a < m <= k and a >= a0
    # the fragment's first keyframe stops being tried once the camera is more than `window` keyframes on; the
    # newest keyframe is paired with the window's start, its middle, and two keyframes back (fast motion)
    assert B.init_pairs(0, 20, 8, 3) == [(12, 20), (16, 20), (18, 20)]
    assert B.init_pairs(0, 4, 8, 3) == [(0, 4), (2, 4), (0, 3)]


def _build(frames=24, warmup=3):
    """A mapper over the exact fakes, every keyframe kept; the bootstrap's constants as the test set them."""
    pcfg = validate_pipeline({"graph": {"init": {"warmup": warmup}, "ba_downsample": 4,
                                        "keyframes": {"redundant_thresh": 0.0}}})
    ds = fakes.FakeDataset(fakes.FakeDatasetConfig(frames=frames, speed=0.4))
    fe = fakes.ExactFrontend(fakes.ExactFrontendConfig(keyframe_every=2), ds=4)
    spec = get_registry().get("optimizer", "online_ba")
    opt = spec.factory(spec.config_model(), BuildContext(device=torch.device("cpu")))
    return Mapper(pcfg, ds.info(), fe, opt, None, "cpu"), ds


def _record_pairs(monkeypatch, tried: list, last: int = 0):
    """Record each keyframe pair the bootstrap observes on its own, ``(a, m)`` (``last``: ``m`` only), while the
    map is not initialised; returns the box where the test puts the mapper (``box["m"]``)."""
    box = {}
    real = EdgeObserver.observe_pair

    def observe_pair(self, a, b):
        if not box["m"].initialized:
            tried.append(b if last else (int(a), int(b)))
        return real(self, a, b)

    monkeypatch.setattr(EdgeObserver, "observe_pair", observe_pair)
    return box


@pytest.fixture(autouse=True)
def _no_loop_suppression(monkeypatch):
    monkeypatch.setattr(loops, "NMS_KEYFRAMES", 0)


def test_initialises_on_a_later_pair_and_places_the_earlier_keyframes(monkeypatch, caplog):
    """The first two keyframes never pair (as if the camera had turned away from them): the map initialises on a
    later pair, says why before, and the keyframes before the pair are placed from their own flow to it, so the
    whole trajectory is right up to scale."""
    tried: list[tuple[int, int]] = []
    real = B.two_view_init_why
    box = _record_pairs(monkeypatch, tried)  # the bootstrap observes exactly the pair it then hands on

    def why(target, weight, intr, opts):
        a, m = tried[-1]
        if a < 2 or m < 6:
            return None, "0 confident correspondences < 60 (the views do not overlap)"
        return real(target, weight, intr, opts)

    monkeypatch.setattr(B, "two_view_init_why", why)
    monkeypatch.setattr(B, "INIT_WINDOW", 3)
    monkeypatch.setattr(B, "INIT_TRIES", 2)
    m, ds = _build()
    box["m"] = m
    with caplog.at_level(logging.INFO, logger="pvslam"):
        results = [m.process(f, None) for f in ds]
    first_init = next(i for i, r in enumerate(results) if r.initialized)
    assert first_init == 12  # keyframe 6 (every second frame): the first with a pair (a >= 2, m >= 6)
    assert any("map not initialised yet" in r.message and "do not overlap" in r.message for r in caplog.records)
    assert any("pair 3-6" in r.message for r in caplog.records if "map initialised" in r.message)
    m.finalize()
    _, poses = m.trajectory()
    gt = torch.stack([f.gt_pose for f in ds])
    ate = umeyama_ate(poses[:, :3], gt[:, :3])
    assert ate < 1e-3 * float((gt[-1, :3] - gt[0, :3]).norm()), ate


def test_earlier_keyframe_without_a_pose_keeps_its_neighbours(monkeypatch):
    """When a keyframe before the pair cannot be placed (motion-only BA fails), it takes the pose of the keyframe
    after it (no crash: that pose is copied, not written through a view of the graph's own storage)."""
    real = B.two_view_init_why
    tried: list[tuple[int, int]] = []
    box = _record_pairs(monkeypatch, tried)

    def why(target, weight, intr, opts):
        a, m = tried[-1]
        return (None, "refused") if a < 2 else real(target, weight, intr, opts)

    monkeypatch.setattr(B, "two_view_init_why", why)
    monkeypatch.setattr(B, "INIT_WINDOW", 2)
    monkeypatch.setattr(B, "INIT_TRIES", 1)
    m, ds = _build(frames=16)
    box["m"] = m
    monkeypatch.setattr(m.state.frames, "motion_only", lambda *a, **k: None)
    placed = []  # the poses as the bootstrap left them (the window BA after it moves them)
    monkeypatch.setattr(m.window_ba, "optimize", lambda k, rounds: placed.append(m.graph.poses.clone()))
    for f in ds:
        m.process(f, None)
        if m.initialized:
            break
    assert m.initialized and placed
    a = next(a for a, _ in reversed(tried) if a >= 2)  # the pair that initialised
    poses = placed[0]
    assert not torch.equal(poses[a], poses[a + 1])  # the pair has a baseline
    for j in range(a):  # every keyframe before the pair took the pose of the one after it (= the pair's first)
        assert torch.equal(poses[j], poses[a])


def test_warmup_ends_at_warmup_keyframes_or_three_spanning_warmup_seconds(monkeypatch):
    """Keyframes every 0.2 s (10 frames/s, every second frame): with ``warmup = 5`` the first initialisation is
    tried at keyframe 4, unless at least 3 keyframes span ``warmup_seconds`` first (a slow camera makes keyframes
    rarely: collecting 5 of them took 2.1 s on a textureless room)."""
    def first_try(warmup_seconds):
        tried: list[int] = []
        monkeypatch.undo()  # one recorder at a time
        box = _record_pairs(monkeypatch, tried, last=1)
        monkeypatch.setattr(B, "WARMUP_SECONDS", warmup_seconds)
        monkeypatch.setattr(loops, "NMS_KEYFRAMES", 0)
        m, ds = _build(frames=16, warmup=5)
        box["m"] = m
        for f in ds:
            m.process(f, None)
        assert m.initialized
        return tried[0]

    assert first_try(warmup_seconds=0) == 4  # keyframes 0..4: the count alone
    assert first_try(warmup_seconds=0.4) == 2  # 3 keyframes (0, 0.2, 0.4 s) already span 0.4 s
    assert first_try(warmup_seconds=0.5) == 3  # 4 keyframes span 0.6 s
    assert first_try(warmup_seconds=5.0) == 4  # never before the count


def test_with_the_chain_check_the_pairs_between_are_observed_then_discarded_and_the_map_initialises(monkeypatch):
    """bootstrap.CHAIN_TOL > 0: each pair tried is followed by one observation of its consecutive keyframe pairs
    (bootstrap.chain_checked), which the frontend is then told to discard (observed before the map existed); on
    exact flow the map initialises as without it, at the same frame, and its trajectory is right up to scale."""
    def run(tol):
        monkeypatch.setattr(B, "CHAIN_TOL", tol)
        m, ds = _build()
        fe = m.frontend
        chains, discarded = [], []
        real_observe, real_discard = fe.observe, fe.discard_pairs

        def observe(graph, ii, jj):
            if not m.initialized and len(ii) > 1:
                chains.append((ii.tolist(), jj.tolist()))
            return real_observe(graph, ii, jj)

        def discard(src, dst):
            discarded.append((src.tolist(), dst.tolist()))
            return real_discard(src, dst)

        monkeypatch.setattr(fe, "observe", observe)
        monkeypatch.setattr(fe, "discard_pairs", discard)
        results = [m.process(f, None) for f in ds]
        m.finalize()
        return m, chains, discarded, next(i for i, r in enumerate(results) if r.initialized)

    m, chains, discarded, first = run(1.0)
    assert chains and len(discarded) == len(chains)
    for ii, jj in chains:  # consecutive keyframes a -> a+1 -> ... -> m
        assert jj == [i + 1 for i in ii] and len(ii) >= 2
    ids = m.graph.ids.tolist()
    assert discarded[0] == ([ids[i] for i in chains[0][0]], [ids[j] for j in chains[0][1]])
    m0, chains0, _, first0 = run(0.0)
    assert not chains0 and first0 == first
    _, ds = _build()
    gt = torch.stack([f.gt_pose for f in ds])
    for mm in (m, m0):  # right up to scale both (the chain drops what leaves the view: another median depth)
        ate = umeyama_ate(mm.trajectory()[1][:, :3], gt[:, :3])
        assert ate < 1e-3 * float((gt[-1, :3] - gt[0, :3]).norm()), ate


def test_a_pair_whose_direct_flow_is_lost_initialises_on_its_chained_links(monkeypatch, caplog):
    """bootstrap.CHAIN_FALLBACK: before the map exists nothing starts a far pair's flow from the motion, and it can
    come back with no confident pixel while each link between is fine (a 45 deg lens on a hand-held camera).  The
    pair then initialises on the chained links' correspondences: on exact links the map starts at the same frame
    and on the same pair as with the direct flow, right up to scale; without the fallback that pair is declined."""
    def run(wipe, fallback):
        monkeypatch.setattr(B, "CHAIN_TOL", 1.0)
        monkeypatch.setattr(B, "CHAIN_FALLBACK", fallback)
        m, ds = _build()
        fe = m.frontend
        real_observe = fe.observe

        def observe(graph, ii, jj):
            obs = real_observe(graph, ii, jj)
            if wipe and not m.initialized and len(ii) == 1 and int(jj[0]) - int(ii[0]) > 1:
                obs.weight.zero_()  # the far pair's direct flow: nothing confident
            return obs

        monkeypatch.setattr(fe, "observe", observe)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="pvslam"):
            results = [m.process(f, None) for f in ds]
        m.finalize()
        said = next(r.getMessage() for r in caplog.records if "map initialised" in r.getMessage())
        return m, said, next(i for i, r in enumerate(results) if r.initialized)

    m_ref, said_ref, first_ref = run(wipe=False, fallback=True)
    m_fb, said_fb, first_fb = run(wipe=True, fallback=True)
    _, said_off, first_off = run(wipe=True, fallback=False)
    pair = said_ref.split("(pair ")[1].split(",")[0]
    a, k = (int(x) for x in pair.split("-"))
    assert k - a > 1  # the reference starts on a far pair (the one the wiped runs lose)
    assert first_fb == first_ref and f"(pair {pair}," in said_fb
    assert f"(pair {pair}," not in said_off  # declined without the fallback: an adjacent pair or a later keyframe
    _, ds = _build()
    gt = torch.stack([f.gt_pose for f in ds])
    ate = umeyama_ate(m_fb.trajectory()[1][:, :3], gt[:, :3])
    assert ate < 1e-3 * float((gt[-1, :3] - gt[0, :3]).norm()), ate
