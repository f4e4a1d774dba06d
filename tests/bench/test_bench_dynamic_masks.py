"""bench_dynamic_masks counts what the masks take: per ground-truth category the static pixels removed, the moving
pixels kept and the share of static confidence lost, against a hand-made keyframe whose answer is written here."""
from __future__ import annotations

import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_dynamic_masks as B  # noqa: E402


def test_tally_counts_false_dynamic_missed_and_lost_confidence():
    t = B.Tally()
    h, w = 2, 4
    moving = torch.tensor([[False, False, True, True], [False, False, False, False]])
    cat = torch.tensor([[1, 1, 11, 11], [3, 3, 3, 3]])  # road, road, car, car / building x 4
    in_thing = torch.tensor([[False, True, True, True], [False, False, False, False]])
    t.kf[7] = (moving, cat, in_thing)
    dyn = torch.tensor([[[1.0, 1.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0]]])  # both road pixels, one car pixel
    conf = torch.full((1, h, w), 0.5)
    weight = torch.where(dyn > 0, torch.full_like(conf, 0.1), conf)
    t.observe([(7, 8)], dyn, conf, weight)
    t.observe([(99, 7)], dyn, conf, weight)  # a keyframe without ground truth is not counted
    s = B.summarise(t, {1: "road", 3: "building", 11: "car"})
    road, car, bldg = s["categories"]["road"], s["categories"]["car"], s["categories"]["building"]
    assert road["false_dyn"] == 1.0 and road["by_thing"] == 0.5 and road["missed"] is None
    assert car["missed"] == 0.5 and car["static_px"] == 0
    assert bldg["false_dyn"] == 0.0
    # static confidence 6 x 0.5 = 3.0, of which the two road pixels lost 2 x 0.4
    assert abs(s["w_lost_static"] - 0.8 / 3.0) < 1e-6 and abs(s["w_lost_scale_bearing"] - 0.8 / 3.0) < 1e-6  # float32
    assert abs(s["all_pixels"]["removed"] - 3 / 8) < 1e-9 and abs(s["all_pixels"]["removed_in_thing"] - 2 / 8) < 1e-9
