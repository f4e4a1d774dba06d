"""The ``classical`` loop detector on the built-in synthetic ``driving_loop`` (GT revisit pairs in loops.json)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pvslam_core.types import Frame, Intrinsics
from pvslam_plugins.loops.classical.config import ClassicalLoopConfig
from pvslam_plugins.loops.classical.detector import ClassicalLoopDetector

generator = pytest.importorskip("pvslam_plugins.datasets.synthetic.generator")

STEP = 3  # every 3rd frame is a keyframe


@pytest.fixture(scope="module")
def loop_sequence():
    # the default request, so the cached sequence is shared with other tests and `pvslam run`
    root = Path(generator.generate("driving_loop", progress=False))
    names = sorted((root / "rgb").glob("*.png"))
    gt = np.loadtxt(root / "groundtruth.txt", comments="#")
    fx, fy, cx, cy = np.loadtxt(root / "calib.txt", comments="#").reshape(-1)[:4]
    pairs = np.array(json.loads((root / "loops.json").read_text())["pairs"], dtype=np.int64).reshape(-1, 2)
    keep = list(range(0, len(names), STEP))
    imgs = [cv2.cvtColor(cv2.imread(str(names[i]), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) for i in keep]
    h, w = imgs[0].shape[:2]
    K = Intrinsics(float(fx), float(fy), float(cx), float(cy), w, h)
    return dict(idx=np.array(keep), imgs=imgs, ts=gt[:, 0], centres=gt[:, 1:4], pairs=pairs, K=K)


@pytest.mark.slow
def test_revisit_pairs_score_higher_than_other_pairs(loop_sequence):
    s = loop_sequence
    idx, pairs = s["idx"], s["pairs"]
    assert len(pairs) > 0, "the driving loop should revisit its start"
    det = ClassicalLoopDetector()
    D = np.stack([det.descriptor(im) for im in s["imgs"]])
    S = D @ D.T
    pos = {int(f): n for n, f in enumerate(idx)}
    rev = np.zeros_like(S, dtype=bool)
    for i, j in pairs:
        if int(i) in pos and int(j) in pos:
            rev[pos[int(i)], pos[int(j)]] = True
    assert rev.sum() >= 5
    fi, fj = np.meshgrid(idx, idx, indexing="ij")
    dist = np.linalg.norm(s["centres"][fi] - s["centres"][fj], axis=-1)
    other = (fi > fj + 50) & (dist > 15.0)
    sim_rev, sim_other = S[rev], S[other]
    assert np.median(sim_rev) > np.percentile(sim_other, 90), (np.median(sim_rev), np.percentile(sim_other, 90))
    assert sim_rev.mean() > sim_other.mean() + 0.2
    # retrieval: for a query with a GT revisit, the most similar old keyframe is a revisit (or within 5 m)
    hits = total = 0
    for a in np.nonzero(rev.any(axis=1))[0]:
        old = fi[a] > fj[a] + 50
        b = int(np.argmax(np.where(old, S[a], -np.inf)))
        total += 1
        hits += bool(rev[a, b] or dist[a, b] < 5.0)
    assert hits >= 0.8 * total, (hits, total)


@pytest.mark.slow
def test_detector_closes_the_loop(loop_sequence):
    s = loop_sequence
    det = ClassicalLoopDetector(ClassicalLoopConfig())
    loops = []
    for k, (f, im) in enumerate(zip(s["idx"], s["imgs"])):
        fr = Frame(index=int(f), timestamp=float(s["ts"][f]), image=torch.from_numpy(im).permute(2, 0, 1).contiguous(),
                   intrinsics=s["K"])
        det.add_keyframe(k, fr)
        # suppression near accepted loops, as the pipeline's loop policy does (nms_keyframes = 5)
        near = lambda j, k=k: any(abs(lc.i - k) <= 5 and abs(lc.j - j) <= 5 for lc in loops)  # noqa: E731
        loops += [c for c in det.query(k, skip=near) if c.verified][:1]
    assert loops, "no loop closed on the driving loop"
    idx, c = s["idx"], s["centres"]
    d = np.array([np.linalg.norm(c[idx[lc.i]] - c[idx[lc.j]]) for lc in loops])
    assert all(lc.verified and lc.i > lc.j for lc in loops)
    assert (d < 5.0).sum() >= 3  # the revisit of the start is found ...
    # ... and look-alike places elsewhere are rare (the block is laid out almost point-symmetrically, so a few
    # geometrically consistent look-alikes exist; see the brief's section 5 on false positives)
    assert (d > 15.0).sum() <= max(2, len(loops) // 4), [(int(idx[lc.i]), int(idx[lc.j]), x) for lc, x in zip(loops, d)]
