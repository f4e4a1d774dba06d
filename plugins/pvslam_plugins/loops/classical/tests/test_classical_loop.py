"""Tests of the ``classical`` loop detector (descriptor, verification, temporal exclusion, id bookkeeping)."""
from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
import skimage.data as skd
import torch

from pvslam_core.types import Frame, Intrinsics
from pvslam_plugins.loops.classical.config import ClassicalLoopConfig
from pvslam_plugins.loops.classical.detector import ClassicalLoopDetector, make_loop_detector
from pvslam_plugins.loops.verification import extract, verify

W, H = 320, 240
K = Intrinsics(fx=288.0, fy=288.0, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)


def _rgb(a: np.ndarray) -> np.ndarray:
    if a.dtype == bool:
        a = a.astype(np.uint8) * 255
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    return np.ascontiguousarray(a[..., :3])


PHOTOS = {n: _rgb(getattr(skd, n)()) for n in ("astronaut", "coffee", "rocket", "chelsea", "camera",
                                               "immunohistochemistry", "hubble_deep_field", "moon")}


def view(name: str, dx: int = 0, dy: int = 0, gain: float = 1.0, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """A 320x240 view of a photo: a crop whose window is shifted by (dx, dy), with exposure change and noise."""
    a = PHOTOS[name]
    y0, x0 = (a.shape[0] - H) // 2 + dy, (a.shape[1] - W) // 2 + dx
    v = a[y0 : y0 + H, x0 : x0 + W].astype(np.float32) * gain
    if noise:
        v += np.random.default_rng(seed).normal(0, noise, v.shape)
    return np.clip(v, 0, 255).astype(np.uint8)


def textured_noise(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((H, W, 3), np.float32)
    for scale in (2, 8, 32):
        small = rng.uniform(0, 255, (H // scale + 1, W // scale + 1, 3)).astype(np.float32)
        img += cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC)[:H, :W] / 3
    return np.clip(img, 0, 255).astype(np.uint8)


def frame(img: np.ndarray, index: int, t: float | None = None) -> Frame:
    return Frame(index=index, timestamp=float(index if t is None else t),
                 image=torch.from_numpy(img).permute(2, 0, 1).contiguous(), intrinsics=K)


def gray(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def cfg(**kw) -> ClassicalLoopConfig:
    base = dict(exclude_recent=3, min_time_gap=0.0)
    base.update(kw)
    return ClassicalLoopConfig(**base)


def step(det: ClassicalLoopDetector, kf_id: int, fr: Frame, skip=None) -> list:
    """Add a keyframe and return its candidates that passed verification (what the loop policy can accept)."""
    det.add_keyframe(kf_id, fr)
    return [c for c in det.query(kf_id, skip) if c.verified]


# ------------------------------------------------------------------------------------------------------------
def test_descriptor_revisit_vs_other_place():
    det = ClassicalLoopDetector()
    thr = det.config.threshold
    for name in PHOTOS:
        d0 = det.descriptor(torch.from_numpy(view(name)).permute(2, 0, 1))
        assert d0.dtype == np.float32 and abs(np.linalg.norm(d0) - 1) < 1e-5
        revisit = det.descriptor(view(name, dx=7, dy=-5, gain=1.15, noise=4.0))
        assert float(d0 @ revisit) >= thr, name
        for other in PHOTOS:
            if other != name:
                assert float(d0 @ det.descriptor(view(other))) < thr, (name, other)
        for s in range(3):
            assert float(d0 @ det.descriptor(textured_noise(s))) < thr, (name, s)


def test_descriptor_accepts_gray_and_numpy_layouts():
    det = ClassicalLoopDetector()
    img = view("coffee")
    d_rgb = det.descriptor(img)
    d_t = det.descriptor(torch.from_numpy(img).permute(2, 0, 1))
    d_g = det.descriptor(gray(img))
    assert np.allclose(d_rgb, d_t) and np.allclose(d_rgb, d_g, atol=1e-5)


def test_verification_accepts_revisit_rejects_other_place():
    a = extract(gray(view("astronaut")), K, 500)
    b = extract(gray(view("astronaut", dx=10, dy=6, gain=0.9, noise=3.0)), K, 500)
    res = verify(a, b, min_inliers=30, min_inlier_ratio=0.3)
    assert res.accepted and res.inliers >= 100, res
    for other in ("coffee", "rocket", "camera"):
        res = verify(a, extract(gray(view(other)), K, 500), min_inliers=30, min_inlier_ratio=0.3)
        assert not res.accepted, (other, res)
    n1, n2 = extract(gray(textured_noise(1)), K, 500), extract(gray(textured_noise(2)), K, 500)
    assert not verify(n1, n2).accepted


def _tour(names=("astronaut", "coffee", "rocket", "chelsea", "camera", "immunohistochemistry")) -> list[np.ndarray]:
    """Distinct places (photos and textured noise), then a revisit of the first place."""
    imgs = [view(n) for n in names] + [textured_noise(s) for s in range(3)]
    return imgs


def test_revisit_detected_and_verified():
    det = ClassicalLoopDetector(cfg())
    tour = _tour()
    for k, img in enumerate(tour):
        assert step(det, k, frame(img, 10 * k)) == []
    k = len(tour)
    loops = step(det, k, frame(view("astronaut", dx=6, dy=4, gain=1.1, noise=3.0), 10 * k))
    assert len(loops) == 1
    lc = loops[0]
    assert (lc.i, lc.j) == (k, 0) and lc.verified and lc.inliers >= 30 and lc.score >= det.config.threshold
    # a new place does not close a loop
    assert step(det, k + 1, frame(textured_noise(7), 10 * (k + 1))) == []
    sim = det.similarity_matrix()
    assert sim.shape == (k + 2, k + 2) and np.allclose(sim, sim.T) and np.allclose(np.diag(sim), 1, atol=1e-5)
    assert sim[k, 0] == pytest.approx(lc.score, abs=1e-6)


def test_verification_rejects_retrieval_false_positive():
    """With threshold -1 every old keyframe is retrieved; only the true revisit survives verification."""
    det = ClassicalLoopDetector(cfg(threshold=-1.0, max_candidates=20))
    tour = _tour()
    for k, img in enumerate(tour):
        det.add_keyframe(k, frame(img, k))
    k = len(tour)
    det.add_keyframe(k, frame(view("coffee", dx=-8, dy=3), k))
    out = det.query(k)
    assert [(lc.i, lc.j) for lc in out if lc.verified] == [(k, 1)]
    assert all(lc.verified is False for lc in out if lc.j != 1)  # checked and failed, never "unknown"
    assert len(det.last_verifications) == k - det.config.exclude_recent
    # the loop policy's skip predicate spares the verification of candidates it would refuse anyway
    det.query(k, skip=lambda j: j != 1)
    assert [v[1] for v in det.last_verifications] == [1]
    unverified = ClassicalLoopDetector(cfg(threshold=-1.0, max_candidates=2, verify=False))
    for kk, img in enumerate(tour):
        unverified.add_keyframe(kk, frame(img, kk))
    unverified.add_keyframe(k, frame(view("coffee", dx=-8, dy=3), k))
    out = unverified.query(k)
    assert len(out) == 2 and all(lc.verified is None for lc in out) and out[0].j == 1  # retrieval only


def test_temporal_exclusion_keyframes_and_seconds():
    tour = [view("astronaut"), view("coffee"), view("rocket")]
    revisit = view("astronaut", dx=5, dy=5)
    # keyframe window: the revisit is 3 keyframes after the original; exclude_recent=3 excludes it, 2 does not
    for excl, expect in ((3, 0), (2, 1)):
        det = ClassicalLoopDetector(cfg(exclude_recent=excl))
        for k, img in enumerate(tour):
            det.add_keyframe(k, frame(img, k, t=100.0 * k))
        assert len(step(det, 3, frame(revisit, 3, t=300.0))) == expect, excl
    # time window: 3 s after the original with min_time_gap 5 s -> excluded; 6 s -> accepted
    for t_revisit, expect in ((3.0, 0), (6.0, 1)):
        det = ClassicalLoopDetector(cfg(exclude_recent=0, min_time_gap=5.0))
        for k, img in enumerate(tour):
            det.add_keyframe(k, frame(img, k, t=0.5 * k))
        assert len(step(det, 3, frame(revisit, 3, t=t_revisit))) == expect, t_revisit


def test_removed_keyframe_is_forgotten_ids_stay():
    """Keyframes are named by stable id: a removal (graph notification) drops one, the others keep their ids."""
    det = ClassicalLoopDetector(cfg(exclude_recent=1))
    tour = _tour()
    for k, img in enumerate(tour):
        det.add_keyframe(k, frame(img, k))
    n = len(tour)
    det.on_keyframe_removed(1)  # "coffee" goes; "rocket" keeps id 2
    assert len(det) == n - 1 and det.descriptors.shape[0] == n - 1
    assert det.keyframe_ids()[:3] == [0, 2, 3] and det.keyframe_frame_indices()[:3] == [0, 2, 3]
    loops = step(det, n, frame(view("rocket", dx=4, dy=-6), n))
    assert [(lc.i, lc.j) for lc in loops] == [(n, 2)]
    assert det.similarity_matrix().shape == (n, n)
    # a revisit of the removed place finds nothing verified
    assert step(det, n + 1, frame(view("coffee", dx=3), n + 1)) == []
    det.on_keyframe_removed(100)  # unknown ids are ignored
    with pytest.raises(ValueError):  # ids come in time order
        det.add_keyframe(5, frame(view("moon"), 99))
    with pytest.raises(KeyError):
        det.query(1)


def test_registered_and_fast():
    import pvslam_plugins.loops.classical as plugin

    spec_names = []  # call the hook directly: entry points may be filtered by PVSLAM_LOAD_PLUGINS

    def register(name, factory, model, description=""):
        spec_names.append((name, factory, model))

    plugin.register_loop_detectors(register=register)
    assert spec_names[0][0] == "classical"
    det = spec_names[0][1](spec_names[0][2](), None)
    assert isinstance(det, ClassicalLoopDetector)
    with pytest.raises(Exception):
        ClassicalLoopConfig(treshold=0.5)  # typo -> error (extra="forbid")
    # a keyframe without candidates is cheap (brief: < ~5 ms at 320x240; generous bound for loaded CI machines)
    imgs = [textured_noise(s) for s in range(12)]
    det = make_loop_detector(ClassicalLoopConfig(), None)
    t = time.perf_counter()
    for k, img in enumerate(imgs):
        step(det, k, frame(img, k))
    per_call = (time.perf_counter() - t) / len(imgs)
    assert per_call < 0.05, per_call


def test_adaptive_threshold_follows_the_neighbours_similarity(monkeypatch):
    """ADAPTIVE_NEIGHBOURS (ORB-SLAM's rule): a candidate scoring below the fixed threshold is retrieved when the
    new keyframe's own predecessors look no more alike; never below ADAPTIVE_FLOOR."""
    from pvslam_plugins.loops.classical import detector as D

    e = np.eye(6, dtype=np.float32)

    def unit(c, k):  # cosine c to e0, the rest along axis k
        return c * e[0] + np.sqrt(1 - c * c) * e[k]

    # keyframes: place A (0.62 to the query), another place (0.30), two predecessors (0.60, 0.65), the query
    vecs = [unit(0.62, 1), unit(0.30, 2), unit(0.60, 3), unit(0.65, 4), e[0]]

    class Preset(ClassicalLoopDetector):
        def descriptor(self, image):
            return vecs[self._n]

    def retrieved(adaptive_neighbours=D.ADAPTIVE_NEIGHBOURS, adaptive_floor=D.ADAPTIVE_FLOOR, **kw):
        monkeypatch.setattr(D, "ADAPTIVE_NEIGHBOURS", adaptive_neighbours)
        monkeypatch.setattr(D, "ADAPTIVE_FLOOR", adaptive_floor)
        det = Preset(cfg(exclude_recent=2, verify=False, **kw))  # the predecessors are no candidates
        for k in range(5):
            det._n = k
            det.add_keyframe(k, frame(view("astronaut"), k))
        return [(c.j, round(c.score, 2)) for c in det.query(4)]

    assert retrieved(adaptive_neighbours=0) == []  # the fixed threshold (0.75)
    assert retrieved() == [(0, 0.62)]  # the default, 2 neighbours: threshold min(0.75, 0.60, 0.65) = 0.60
    assert retrieved(adaptive_neighbours=1) == []  # the last predecessor alone: 0.65
    assert retrieved(adaptive_floor=0.7) == []
    assert retrieved(threshold=0.2, adaptive_floor=0.7) == [(0, 0.62), (1, 0.3)]  # it never raises a lower threshold


def test_adaptive_candidates_must_be_a_revisit_not_a_distant_view(monkeypatch):
    """A candidate retrieved only through the adaptive threshold passes verification only when the new view sees
    the matched structure about as large as the old one (ADAPTIVE_MIN_SPREAD); above `threshold` the spread is not
    asked."""
    from pvslam_plugins.loops.verification import Verification

    for score_above, spread, expect in ((False, 0.8, False), (False, 0.95, True), (True, 0.8, True)):
        det = ClassicalLoopDetector(cfg(exclude_recent=0, threshold=0.5 if score_above else 0.999))
        for k, name in enumerate(("astronaut", "coffee")):
            det.add_keyframe(k, frame(view(name), k))
        det.add_keyframe(2, frame(view("astronaut", dx=4), 2))
        monkeypatch.setattr(det, "_threshold", lambda r: 0.5)  # the adaptive threshold, whatever the neighbours
        monkeypatch.setattr(det.verifier, "verify", lambda i, j, s=spread: Verification(True, 200, 150, "", s))
        got = [c for c in det.query(2) if c.j == 0]
        assert len(got) == 1 and got[0].verified is expect, (score_above, spread)


def test_verification_reports_how_large_the_new_view_sees_the_match():
    """Verification.spread: the inliers' spread in the first view over that in the second, ~1 for a revisit from the
    same spot, ~0.7 when the first view is the same place 0.7x as large (seen from farther away)."""
    near = view("astronaut")
    small = cv2.resize(near, None, fx=0.7, fy=0.7, interpolation=cv2.INTER_AREA)
    far = np.full_like(near, 128)
    y0, x0 = (H - small.shape[0]) // 2, (W - small.shape[1]) // 2
    far[y0:y0 + small.shape[0], x0:x0 + small.shape[1]] = small  # zoomed out about the image centre
    fa, fb, fs = (extract(gray(v), K, 1000) for v in (far, near, view("astronaut", dx=6, dy=-4)))
    res = verify(fa, fb)
    assert res.accepted and abs(res.spread - 0.7) < 0.07, res
    shifted = verify(fs, fb)
    assert shifted.accepted and abs(shifted.spread - 1.0) < 0.05, shifted
