"""bench_vps: the heads scored side by side on one run, in the plain generator's look or a held-out one."""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_vps as B  # noqa: E402


def test_a_run_in_the_held_out_look_scores_every_head_on_other_frames(single_torch_thread):
    plain = B.run_sequence("moving_vehicles", 400, 3, {})
    held = B.run_sequence("moving_vehicles", 400, 3, {}, domain="heldout")
    assert plain["domain"] is None and held["domain"] == "heldout"
    assert held["frames"] == plain["frames"] == 3
    assert set(held["heads"]) == set(B.HEADS)
    for head in B.HEADS:
        assert 0.0 <= held["heads"][head]["vpq"] <= 1.0
    # the same scene in another look: the segmenter's own per-frame result differs
    assert held["heads"]["none"]["pq"] != plain["heads"]["none"]["pq"]
