"""Loop-closure precision / recall on hand-made cases."""
from __future__ import annotations

import math

import pytest

from pvslam_core.evaluation.loops import loop_precision_recall, revisit_events
from pvslam_core.types import LoopCandidate

# Two revisit events: frames 200..209 revisit 10..19, and frames 400..404 revisit 100..104.
GT = [(200 + k, 10 + k) for k in range(10)] + [(400 + k, 100 + k) for k in range(5)]


def test_events_are_connected_runs():
    ev = revisit_events(GT, tolerance=5)
    assert len(ev) == 2
    assert len(ev[0]) == 10 and len(ev[1]) == 5
    # Same older place revisited twice, far apart in time: two events.
    assert len(revisit_events([(100, 10), (101, 11), (300, 10), (301, 11)], tolerance=5)) == 2
    # With tolerance 0 only identical pairs link: a run stepping by one frame falls apart.
    assert len(revisit_events([(100, 10), (101, 11)], tolerance=0)) == 2
    assert revisit_events([], 5) == []


def test_precision_recall_known_case():
    detected = [
        (203, 12),  # matches (203, 13) within 5 in both indices -> TP, event 1
        (12, 205),  # order does not matter: (205, 12) -> TP, event 1
        (300, 150),  # nowhere near a GT pair -> FP
        (207, 30),  # i fine, j off by 13 from (207, 17) -> FP
    ]
    r = loop_precision_recall(detected, GT, tolerance=5)
    assert r["num_detected"] == 4 and r["num_tp"] == 2 and r["num_fp"] == 2
    assert r["precision"] == pytest.approx(0.5)
    assert r["num_gt_events"] == 2 and r["num_events_detected"] == 1
    assert r["recall"] == pytest.approx(0.5)
    assert r["f1"] == pytest.approx(0.5)
    # GT pairs within 5 of (203,12) or (205,12): i in 198..210 and j in 7..17 -> k = 0..7 -> 8 of 15.
    assert r["pair_recall"] == pytest.approx(8 / 15)
    assert sorted(r["false_positives"]) == [(207, 30), (300, 150)]


def test_tolerance_boundaries_and_loop_candidates():
    gt = [(100, 10)]
    assert loop_precision_recall([(105, 15)], gt, tolerance=5)["precision"] == 1.0
    assert loop_precision_recall([(106, 15)], gt, tolerance=5)["precision"] == 0.0
    assert loop_precision_recall([(100, 10)], gt, tolerance=0)["recall"] == 1.0
    r = loop_precision_recall([LoopCandidate(i=101, j=9, score=0.9, verified=True)], gt, tolerance=1)
    assert r["num_tp"] == 1 and r["recall"] == 1.0


def test_perfect_and_duplicates():
    r = loop_precision_recall(GT + GT, GT, tolerance=5)
    assert r["num_detected"] == 15  # exact duplicates counted once
    assert r["precision"] == 1.0 and r["recall"] == 1.0 and r["pair_recall"] == 1.0 and r["f1"] == 1.0


def test_empty_cases():
    r = loop_precision_recall([], GT)
    assert math.isnan(r["precision"]) and r["recall"] == 0.0 and math.isnan(r["f1"])
    r = loop_precision_recall([(50, 1)], [])
    assert r["precision"] == 0.0 and math.isnan(r["recall"]) and r["num_fp"] == 1


def _events_by_brute_force(pairs, tol):
    """Connected components of the Chebyshev-within-tol relation, listed in the order of their first pair."""
    import numpy as np

    gt = np.unique(np.array([(max(a, b), min(a, b)) for a, b in pairs]), axis=0)
    label = list(range(len(gt)))

    def find(x):
        while label[x] != x:
            x = label[x]
        return x

    for a in range(len(gt)):
        for b in range(a + 1, len(gt)):
            if np.abs(gt[a] - gt[b]).max() <= tol:
                label[find(b)] = find(a)
    roots = [find(a) for a in range(len(gt))]
    order = list(dict.fromkeys(roots))  # first appearance in sorted order
    return [gt[[r == c for r in roots]] for c in order]


@pytest.mark.parametrize("seed", range(6))
def test_events_equal_the_components_of_every_link(seed):
    import numpy as np

    rng = np.random.default_rng(seed)
    for _ in range(20):
        n, tol, span = int(rng.integers(1, 120)), int(rng.integers(0, 7)), int(rng.integers(5, 120))
        pairs = [tuple(p) for p in rng.integers(0, span, (n, 2))]
        want = _events_by_brute_force(pairs, tol)
        got = revisit_events(np.array(pairs), tol)
        assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))
        assert all(np.array_equal(a, b) for a, b in zip(revisit_events(pairs, tol), want))  # tuples as arrays


def test_events_of_a_long_loops_ground_truth_do_not_list_every_link():
    """A repeated loop: every frame of laps 2..n revisits ~30 frames of each earlier lap (hundreds of thousands of
    pairs, each within the tolerance of ~100 others): the events come out without a Python object or an array row
    per link."""
    import tracemalloc

    import numpy as np

    lap, laps = 400, 12
    i = np.arange(lap, lap * laps)
    rows = [np.stack([i, i - k * lap + d], 1) for k in range(1, laps) for d in range(-15, 15)]
    pairs = np.concatenate(rows)
    pairs = pairs[(pairs[:, 1] >= 0) & (pairs[:, 1] < pairs[:, 0] - 50)]
    tracemalloc.start()
    events = revisit_events(pairs, 5)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    # one event per lap difference: frame i revisits i - k lap for every k, a diagonal band through all laps
    assert len(events) == laps - 1 and sum(len(e) for e in events) == len(np.unique(pairs, axis=0))
    assert peak < 160 * len(pairs), (peak, len(pairs))  # listing the links costs ~2 KB per pair


def test_a_long_runs_loop_metrics_cost_bytes_per_pair(tmp_path):
    """A run's loop metrics against a repeated loop's ground truth (an int64 array of hundreds of thousands of
    pairs, as the run directory holds it): no Python object per pair (a list of rows cost ~280 bytes a pair and
    most of a 10 000-frame run's peak memory), the same figures as for the pairs given as tuples."""
    import json
    import tracemalloc

    import numpy as np

    from pvslam_core.evaluation.run_eval import _loop_metrics

    lap, laps = 400, 12
    i = np.arange(lap, lap * laps)
    pairs = np.concatenate([np.stack([i, i - k * lap + d], 1) for k in range(1, laps) for d in range(-15, 15)])
    pairs = pairs[(pairs[:, 1] >= 0) & (pairs[:, 1] < pairs[:, 0] - 50)]
    detected = [(int(a), int(b)) for a, b in pairs[::5000]] + [(1000, 990), (3000, 2000)]
    (tmp_path / "loops.json").write_text(json.dumps({"loops": [
        {"kf_i": n, "kf_j": n + 1, "frame_i": a, "frame_j": b, "score": 1.0} for n, (a, b) in enumerate(detected)]}))
    tracemalloc.start()
    got = _loop_metrics(tmp_path, pairs, 5)["loops"]
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    want = loop_precision_recall(detected, [tuple(p) for p in pairs.tolist()], 5)
    assert got == want
    assert got["num_fp"] == 2 and got["num_gt_events"] == laps - 1
    assert peak < 150 * len(pairs), (peak, len(pairs))
