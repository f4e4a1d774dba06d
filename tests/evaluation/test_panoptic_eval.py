"""PQ / VPQ known-answer tests (values computed by hand in the comments)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pvslam_core.evaluation.panoptic import pq, vpq
from pvslam_core.types import Category, PanopticSegmentation, Segment

CATS = [
    Category(1, "road", False, (128, 64, 128)),
    Category(2, "car", True, (0, 0, 142)),
    Category(3, "person", True, (220, 20, 60)),
]


def seg(ids, cats: dict[int, int]) -> PanopticSegmentation:
    isthing = {c.id: c.isthing for c in CATS}
    return PanopticSegmentation(
        ids=torch.as_tensor(np.asarray(ids), dtype=torch.int64),
        segments=[Segment(i, c, isthing[c]) for i, c in cats.items()],
    )


# GT: road (id 1, 12 px), car id 2 (6 px), car id 3 (4 px), void 2 px.
GT = seg(
    [
        [1, 1, 1, 1, 1, 1],
        [1, 1, 1, 1, 1, 1],
        [2, 2, 2, 0, 3, 3],
        [2, 2, 2, 0, 3, 3],
    ],
    {1: 1, 2: 2, 3: 2},
)
# Prediction: road 10 (11 px), person 11 (1 px), car 20 (4 px), person 30 (2 px), car 40 (3 px, 1 on void).
PRED = seg(
    [
        [10, 10, 10, 10, 10, 10],
        [10, 10, 10, 10, 10, 11],
        [20, 20, 0, 0, 30, 30],
        [20, 20, 0, 40, 40, 40],
    ],
    {10: 1, 11: 3, 20: 2, 30: 3, 40: 2},
)


def test_pq_hand_built_case():
    r = pq([PRED], [GT], CATS)
    pc = r["per_category"]
    # road: |g∩p| = 11, union = 11 + 12 - 11 = 12 -> IoU 11/12 > 0.5: TP.
    assert (pc[1]["tp"], pc[1]["fp"], pc[1]["fn"]) == (1, 0, 0)
    assert pc[1]["pq"] == pytest.approx(11 / 12)
    # car: gt 2 vs pred 20: 4 / (4 + 6 - 4) = 2/3 -> TP.
    #      gt 3 vs pred 40: |∩| = 2, |p ∩ void| = 1, union = 3 + 4 - 2 - 1 = 4 -> IoU 0.5, NOT > 0.5: FN + FP
    #      (pred 40 lies 1/3 on void, <= 1/2, so it is an FP). pred 30 (person) does not match car (category).
    assert (pc[2]["tp"], pc[2]["fp"], pc[2]["fn"]) == (1, 1, 1)
    assert pc[2]["sq"] == pytest.approx(2 / 3)
    assert pc[2]["rq"] == pytest.approx(1 / (1 + 0.5 + 0.5))
    assert pc[2]["pq"] == pytest.approx((2 / 3) / 2)
    # person: never in GT; preds 11 and 30 are two FPs -> PQ 0 and the category counts in the average.
    assert (pc[3]["tp"], pc[3]["fp"], pc[3]["fn"]) == (0, 2, 0)
    assert pc[3]["pq"] == 0.0
    assert r["pq"] == pytest.approx((11 / 12 + 1 / 3 + 0) / 3)
    assert r["things"]["pq"] == pytest.approx((1 / 3 + 0) / 2)
    assert r["stuff"]["pq"] == pytest.approx(11 / 12)
    assert r["all"]["n"] == 3 and r["things"]["n"] == 2 and r["stuff"]["n"] == 1


def test_pq_accumulates_over_frames_and_accepts_tuples():
    r1 = pq([PRED], [GT], CATS)
    frame_tuple = (PRED.ids.numpy(), {10: 1, 11: 3, 20: 2, 30: 3, 40: 2})
    coco_gt = (GT.ids, [{"id": 1, "category_id": 1}, {"id": 2, "category_id": 2}, {"id": 3, "category_id": 2}])
    r2 = pq([PRED, frame_tuple], [GT, coco_gt], [{"id": c.id, "isthing": int(c.isthing), "name": c.name} for c in CATS])
    assert r2["pq"] == pytest.approx(r1["pq"])
    assert r2["per_category"][2]["tp"] == 2 and r2["per_category"][2]["fp"] == 2
    assert r2["num_frames"] == 2


def test_pq_perfect_and_renumbered_ids():
    r = pq([GT], [GT], CATS)
    assert r["pq"] == 1.0 and r["sq"] == 1.0 and r["rq"] == 1.0
    # Ids are opaque: a prediction with other numbers but the same segments is perfect too.
    ren = seg(np.vectorize({0: 0, 1: 7, 2: 1000, 3: 2**24 - 1}.get)(GT.ids.numpy()), {7: 1, 1000: 2, 2**24 - 1: 2})
    assert pq([ren], [GT], CATS)["pq"] == 1.0
    # Person does not occur anywhere: it is left out of the averages.
    assert r["all"]["n"] == 2 and math.isnan(r["per_category"][3]["pq"])


def test_prediction_mostly_on_void_is_not_a_false_positive():
    gt = seg([[1, 1, 0, 0], [1, 1, 0, 0]], {1: 1})
    pred = seg([[1, 1, 5, 5], [1, 1, 5, 1]], {1: 1, 5: 2})  # car 5: 3 px, all on void -> ignored
    r = pq([pred], [gt], CATS)
    assert r["per_category"][2]["fp"] == 0
    # road pred has 1 px on void: union = 5 + 4 - 4 - 1 = 4 -> IoU 1.
    assert r["per_category"][1]["sq"] == pytest.approx(1.0)
    assert r["pq"] == 1.0
    pred2 = seg([[1, 1, 5, 5], [1, 1, 5, 5]], {1: 1, 5: 2})
    gt2 = seg([[1, 1, 0, 0], [1, 1, 1, 1]], {1: 1})  # car 5: half on void -> counted (not > 1/2)
    assert pq([pred2], [gt2], CATS)["per_category"][2]["fp"] == 1


def test_pq_input_errors():
    bad = seg([[1, 9]], {1: 1})  # id 9 has no segment
    with pytest.raises(ValueError, match=r"ids \[9\]"):
        pq([bad], [seg([[1, 1]], {1: 1})], CATS)
    # A GT id without a segment is skipped (panopticapi): the pred segment over it is neither TP nor void-ignored.
    r = pq([seg([[1, 1, 2, 2]], {1: 1, 2: 2})], [(np.array([[1, 1, 9, 9]]), {1: 1})], CATS)
    assert r["per_category"][1]["tp"] == 1 and r["per_category"][2]["fp"] == 1 and r["per_category"][2]["fn"] == 0
    with pytest.raises(ValueError, match="differ in size"):
        pq([seg([[1]], {1: 1})], [seg([[1, 1]], {1: 1})], CATS)
    with pytest.raises(ValueError, match="not in categories"):
        pq([(np.array([[1]]), {1: 99})], [seg([[1]], {1: 1})], CATS)


def moving_car_sequence(n=10, switch_at=None, switch_ids=(7, 8)):
    """Road (stuff) everywhere, a car sliding right one pixel per frame. GT car id 5."""
    gts, preds = [], []
    for t in range(n):
        ids = np.ones((6, 16), np.int64)
        ids[2:4, t : t + 4] = 5
        gts.append(seg(ids, {1: 1, 5: 2}))
        pid = switch_ids[0] if (switch_at is None or t < switch_at) else switch_ids[1]
        p = ids.copy()
        p[p == 5] = pid
        p[p == 1] = 3
        preds.append(seg(p, {3: 1, pid: 2}))
    return preds, gts


def test_vpq_perfect_is_one():
    preds, gts = moving_car_sequence(20)
    r = vpq(preds, gts, CATS)
    assert r["vpq"] == 1.0 and r["vpq_things"] == 1.0 and r["vpq_stuff"] == 1.0
    assert r["ks"] == [0, 5, 10, 15]
    assert [r["per_k"][k]["num_windows"] for k in r["ks"]] == [20, 15, 10, 5]


def test_vpq_id_switch_lowers_vpq_not_pq():
    preds, gts = moving_car_sequence(10, switch_at=5)
    r = vpq(preds, gts, CATS, ks=(0, 1, 3))
    # k = 0: every frame is perfect (identity does not matter within a frame).
    assert r["per_k"][0]["pq"] == 1.0
    assert pq(preds, gts, CATS)["pq"] == 1.0
    # k = 1: 9 windows. The 8 windows not straddling the switch: car tube TP (IoU 1).
    # Window (4, 5): the GT tube is split in two halves by ids 7 / 8 -> IoU 0.5 each, no match: 1 FN + 2 FP.
    car = r["per_k"][1]["per_category"][2]
    assert (car["tp"], car["fp"], car["fn"]) == (8, 2, 1)
    assert car["pq"] == pytest.approx(8 / (8 + 1 + 0.5))
    assert r["per_k"][1]["stuff"]["pq"] == 1.0
    assert r["per_k"][1]["pq"] == pytest.approx((1 + 8 / 9.5) / 2)
    # k = 3: 7 windows of 4 frames; starts 0, 1, 5, 6 are clean (4 TP, IoU 1). Starts 2 and 4 split the tube
    # 3/4 + 1/4: the larger part matches (TP, IoU 3/4) and the smaller is an FP. Start 3 splits it 2/4 + 2/4:
    # no match (1 FN, 2 FP). Car: TP 6, FP 4, FN 1, IoU sum 4 + 2 * 3/4 = 5.5.
    car3 = r["per_k"][3]["per_category"][2]
    assert (car3["tp"], car3["fp"], car3["fn"]) == (6, 4, 1)
    assert car3["pq"] == pytest.approx(5.5 / (6 + 2 + 0.5))
    assert r["per_k"][3]["pq"] < 1.0
    assert r["vpq"] == pytest.approx(np.mean([r["per_k"][k]["pq"] for k in (0, 1, 3)]))
    assert r["vpq"] < 1.0


def test_vpq_skips_k_longer_than_sequence():
    preds, gts = moving_car_sequence(4)
    r = vpq(preds, gts, CATS, ks=(0, 5))
    assert r["per_k"][5]["num_windows"] == 0
    assert r["vpq"] == 1.0


def _reference_window_stats(frames_pred, frames_gt, cat_of_pred, cat_of_gt):
    """Literal definition: concatenate the window's frames side by side and match segments (COCO rules)."""
    g = np.concatenate(frames_gt, axis=1).reshape(-1)
    p = np.concatenate(frames_pred, axis=1).reshape(-1)
    stats = {}

    def add(c, key, v):
        stats.setdefault(c, {"tp": 0, "fp": 0, "fn": 0, "iou": 0.0})[key] += v

    gt_ids = [i for i in np.unique(g) if i != 0]
    pr_ids = [i for i in np.unique(p) if i != 0]
    matched_g, matched_p = set(), set()
    for gi in gt_ids:
        for pi in pr_ids:
            if cat_of_gt[gi] != cat_of_pred[pi]:
                continue
            inter = np.sum((g == gi) & (p == pi))
            union = np.sum(g == gi) + np.sum(p == pi) - inter - np.sum((g == 0) & (p == pi))
            if inter / union > 0.5:
                add(cat_of_gt[gi], "tp", 1)
                add(cat_of_gt[gi], "iou", inter / union)
                matched_g.add(gi)
                matched_p.add(pi)
    for gi in gt_ids:
        if gi not in matched_g:
            add(cat_of_gt[gi], "fn", 1)
    for pi in pr_ids:
        if pi not in matched_p and np.sum((g == 0) & (p == pi)) / np.sum(p == pi) <= 0.5:
            add(cat_of_pred[pi], "fp", 1)
    return stats


def test_vpq_matches_literal_concatenation_on_random_sequences():
    rng = np.random.default_rng(7)
    n, h, w = 7, 10, 12
    cat_gt = {1: 1, 2: 1, 10: 2, 11: 2, 12: 3}
    cat_pr = {1: 1, 3: 1, 20: 2, 21: 2, 22: 3, 23: 2}
    gts, preds = [], []
    for t in range(n):
        g = rng.choice([0, 1, 2, 10, 11, 12], size=(h, w), p=[0.1, 0.3, 0.2, 0.2, 0.1, 0.1])
        g[: h // 2, : w // 2] = 10  # a persistent block so that some tubes match
        pr = g.copy()
        pr = np.vectorize({0: 0, 1: 1, 2: 3, 10: 20, 11: 21, 12: 22}.get)(pr)
        noise = rng.random((h, w)) < 0.25
        pr[noise] = rng.choice([0, 1, 3, 20, 21, 22, 23], size=noise.sum())
        if t >= 4:
            pr[pr == 20] = 23  # id switch
        gts.append((g, cat_gt))
        preds.append((pr, cat_pr))
    ks = (0, 1, 2, 4)
    r = vpq(preds, gts, CATS, ks=ks)
    for k in ks:
        total = {}
        for i in range(n - k):
            st = _reference_window_stats([p for p, _ in preds[i : i + k + 1]], [g for g, _ in gts[i : i + k + 1]],
                                         cat_pr, cat_gt)
            for c, d in st.items():
                for key, v in d.items():
                    total.setdefault(c, {"tp": 0, "fp": 0, "fn": 0, "iou": 0.0})[key] += v
        for c, d in total.items():
            got = r["per_k"][k]["per_category"][c]
            assert (got["tp"], got["fp"], got["fn"]) == (d["tp"], d["fp"], d["fn"]), (k, c)
            assert got["iou_sum"] == pytest.approx(d["iou"])
