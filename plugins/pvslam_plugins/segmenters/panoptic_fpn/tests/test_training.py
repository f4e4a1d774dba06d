"""Training pieces against references written here: box coding, matching, sampling, mask targets, panoptic
targets, augmentation geometry, the loss on a tiny problem, and the trainer (resume, CSV, plot, evaluation)."""
from __future__ import annotations

import csv
import json

import pytest
import torch

from pvslam_core.types import Segment
from pvslam_plugins.segmenters.panoptic_fpn.categories import CategorySet
from pvslam_plugins.segmenters.panoptic_fpn.data import Augment, panoptic_targets, synthetic_category_set
from pvslam_plugins.segmenters.panoptic_fpn.losses import IGNORE, InstanceTargets, panoptic_fpn_losses
from pvslam_plugins.segmenters.panoptic_fpn.model import PanopticFPN
from pvslam_plugins.segmenters.panoptic_fpn.config import reduced
from pvslam_plugins.segmenters.panoptic_fpn.ops import apply_deltas
from pvslam_plugins.segmenters.panoptic_fpn.targets import encode_deltas, mask_targets, match, subsample
from pvslam_plugins.segmenters.panoptic_fpn.train import TrainConfig, lr_at, run, schedule_progress

from _refs import iou_ref, roi_align_ref


def boxes(n: int, seed: int, extent: float = 60.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * extent
    wh = torch.rand(n, 2, generator=g) * 20 + 1
    return torch.cat([xy, xy + wh], dim=1)


def test_encode_deltas_inverts_apply_deltas():
    src, dst = boxes(50, 0), boxes(50, 1)
    for w in [(1.0, 1.0, 1.0, 1.0), (10.0, 10.0, 5.0, 5.0)]:
        d = encode_deltas(src, dst, w)
        assert torch.allclose(apply_deltas(d, src, w), dst, atol=1e-4)
    # hand-computed: a 10x10 box at the origin -> a 20x10 box shifted by 5 px right
    d = encode_deltas(torch.tensor([[0.0, 0, 10, 10]]), torch.tensor([[0.0, 0, 20, 10]]))
    assert torch.allclose(d, torch.tensor([[0.5, 0.0, float(torch.log(torch.tensor(2.0))), 0.0]]))


def match_ref(gt, bx, lo, hi, low_quality):
    g, b = gt.tolist(), bx.tolist()
    iou = [[iou_ref(a, c) for c in b] for a in g]
    labels, matched = [], []
    for j in range(len(b)):
        col = [iou[i][j] for i in range(len(g))]
        best = max(range(len(g)), key=lambda i: (col[i], -i))  # first maximum, as torch.max
        matched.append(best)
        labels.append(1 if col[best] >= hi else (0 if col[best] < lo else -1))
    if low_quality:
        for i in range(len(g)):
            m = max(iou[i])
            for j in range(len(b)):
                if m > 0 and iou[i][j] == m:
                    labels[j] = 1
    return matched, labels


@pytest.mark.parametrize("low_quality", [False, True])
def test_match_equals_reference(low_quality):
    gt = torch.cat([boxes(6, 2), torch.tensor([[200.0, 200, 202, 202]])])  # the last overlaps nothing
    bx = torch.cat([boxes(300, 3), gt[:3] + 0.5])
    matched, labels = match(gt, bx, 0.3, 0.7, low_quality)
    m_ref, l_ref = match_ref(gt, bx, 0.3, 0.7, low_quality)
    assert labels.tolist() == l_ref
    pos = [j for j, v in enumerate(l_ref) if v != 0]
    assert [int(matched[j]) for j in pos] == [m_ref[j] for j in pos]
    m, lab = match(torch.zeros(0, 4), bx, 0.3, 0.7, True)
    assert (lab == 0).all() and m.shape == (bx.shape[0],)


def test_subsample_counts_and_labels():
    labels = torch.tensor([1] * 10 + [0] * 100 + [-1] * 50, dtype=torch.int8)
    g = torch.Generator().manual_seed(0)
    pos, neg = subsample(labels, 32, 0.25, g)
    assert len(pos) == 8 and len(neg) == 24 and (labels[pos] == 1).all() and (labels[neg] == 0).all()
    assert len(set(pos.tolist())) == 8 and len(set(neg.tolist())) == 24
    pos, neg = subsample(labels[:12], 32, 0.5, g)  # too few: all positives, all negatives
    assert sorted(pos.tolist()) == list(range(10)) and sorted(neg.tolist()) == [10, 11]


def test_mask_targets_equal_roi_align_reference():
    g = torch.Generator().manual_seed(4)
    masks = torch.rand(3, 20, 24, generator=g) > 0.6
    bx = torch.tensor([[1.0, 2.0, 15.0, 18.0], [0.0, 0.0, 24.0, 20.0], [5.5, 3.2, 9.1, 7.7], [3.0, 1.0, 20.0, 9.0]])
    idx = torch.tensor([0, 1, 2, 0])
    got = mask_targets(masks, bx, idx, 7)
    rois = torch.cat([idx[:, None].float(), bx], dim=1)
    ref = roi_align_ref(masks[:, None].float(), rois, 7, 1.0, 2, True)[:, 0] >= 0.5
    assert got.shape == (4, 7, 7) and torch.equal(got.bool(), ref)
    assert mask_targets(masks, bx[:0], idx[:0], 7).shape == (0, 7, 7)


def cats_small() -> CategorySet:
    from pvslam_core.types import Category

    return CategorySet.from_categories("t", [Category(1, "road", False), Category(2, "sky", False),
                                             Category(5, "car", True), Category(6, "bus", True)], ["car"])


def test_panoptic_targets_equal_loop_reference():
    cats = cats_small()
    ids = torch.zeros(10, 12, dtype=torch.int64)
    ids[:4] = 2000  # sky
    ids[4:] = 1000  # road
    ids[5:8, 1:4] = 5001  # car
    ids[6:9, 6:11] = 6003  # bus
    ids[9, 0] = 5002  # a one-pixel car (dropped by min_area, stays "things" in the semantic map)
    ids[0, 0] = 777  # an id without a segment -> ignored
    segs = [Segment(2000, 2, False), Segment(1000, 1, False), Segment(5001, 5, True), Segment(6003, 6, True),
            Segment(5002, 5, True)]
    sem, inst = panoptic_targets(ids, segs, cats, min_area=2)
    sem_of = {0: IGNORE, 777: IGNORE, 2000: 2, 1000: 1, 5001: 0, 6003: 0, 5002: 0}
    ref = torch.tensor([[sem_of[int(v)] for v in row] for row in ids])
    assert torch.equal(sem, ref)
    assert inst.classes.tolist() == [0, 1]  # car, bus (contiguous thing classes), in id order
    assert inst.boxes.tolist() == [[1.0, 5.0, 4.0, 8.0], [6.0, 6.0, 11.0, 9.0]]
    assert torch.equal(inst.masks[1], ids == 6003)
    sem, inst = panoptic_targets(torch.full((4, 4), 1000), [Segment(1000, 1, False)], cats)
    assert inst.boxes.shape == (0, 4) and inst.masks.shape == (0, 4, 4) and (sem == 1).all()


def test_augment_keeps_image_and_labels_aligned():
    """Colour jitter off: a flip/scale/crop of an image whose pixel values encode the label must keep them equal."""
    ids = torch.arange(12 * 16).reshape(12, 16) // 7 * 7  # blocks of equal labels
    img = (ids % 251).to(torch.uint8)[None].expand(3, -1, -1).contiguous()
    aug = Augment(scale=(1.0, 1.0), crop=(8, 10), brightness=0, contrast=0, saturation=0, noise=0)
    for seed in range(6):
        x, lab = aug(img, ids, torch.Generator().manual_seed(seed))
        assert x.shape == (3, 8, 10) and lab.shape == (8, 10)
        assert torch.equal(x[0].round().long(), lab % 251)
    x, lab = Augment(scale=(0.75, 0.75), crop=None)(img, ids, torch.Generator().manual_seed(0))
    assert x.shape == (3, 9, 12) and lab.shape == (9, 12) and set(lab.unique().tolist()) <= set(ids.unique().tolist())


def test_losses_finite_and_decrease_on_one_image():
    """A few optimiser steps on one synthetic-looking image: every term is finite and the total goes down."""
    torch.manual_seed(0)
    cats = cats_small()
    cfg = reduced(num_thing_classes=2, num_sem_classes=3, categories="t")
    model = PanopticFPN(cfg, cats).train()
    ids = torch.full((64, 96), 1000, dtype=torch.int64)
    ids[:20] = 2000
    ids[30:50, 10:40] = 5001
    ids[25:55, 55:90] = 6002
    segs = [Segment(1000, 1, False), Segment(2000, 2, False), Segment(5001, 5, True), Segment(6002, 6, True)]
    sem, inst = panoptic_targets(ids, segs, cats)
    img = torch.zeros(3, 64, 96)
    img[:, :20] = 200.0
    img[0, 30:50, 10:40] = 250.0
    img[2, 25:55, 55:90] = 250.0
    batch, sizes, _ = model.preprocess([img])
    opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    totals = []
    for _ in range(8):
        losses = panoptic_fpn_losses(model, batch, sizes, sem[None], [inst], generator=torch.Generator().manual_seed(0))
        assert set(losses) == {"loss_sem_seg", "loss_rpn_cls", "loss_rpn_loc", "loss_cls", "loss_box_reg",
                               "loss_mask"}
        assert all(torch.isfinite(v) for v in losses.values())
        loss = sum(losses.values())
        totals.append(float(loss.detach()))
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert min(totals[4:]) < 0.5 * totals[0], totals  # single steps are noisy (sampled anchors and proposals)
    # an image without things: instance terms are zero-safe, gradients still flow
    empty = InstanceTargets(torch.zeros(0, 4), torch.zeros(0, dtype=torch.int64), torch.zeros(0, 64, 96, dtype=torch.bool))
    losses = panoptic_fpn_losses(model, batch, sizes, torch.ones_like(sem)[None], [empty])
    assert float(losses["loss_box_reg"].detach()) == 0.0 and float(losses["loss_mask"].detach()) == 0.0
    sum(losses.values()).backward()


def test_schedule_ends_on_iterations_or_time():
    cfg = TrainConfig(iterations=1000, warmup=100, lr=1e-3, final_lr_fraction=0.0, time_budget_min=10)
    assert lr_at(cfg, 0, 0.0) == pytest.approx(1e-4)
    assert lr_at(cfg, 100, schedule_progress(cfg, 100, 0.0)) == pytest.approx(1e-3)
    assert lr_at(cfg, 1000, schedule_progress(cfg, 1000, 0.0)) == pytest.approx(0.0, abs=1e-12)
    # half the time budget used after 110 iterations: the cosine is at its middle, whatever the iteration count
    p = schedule_progress(cfg, 110, 300.0)
    assert p == pytest.approx(0.5) and lr_at(cfg, 110, p) == pytest.approx(0.5e-3 * (1 + torch.cos(
        torch.tensor((0.5 - 0.1) / 0.9 * torch.pi)).item()), rel=1e-6)
    with pytest.raises(ValueError, match="held out"):
        TrainConfig(train_seeds=[1, 2], val_seeds=[2, 3])
    with pytest.raises(ValueError, match="unknown synthetic scenarios"):
        TrainConfig(scenarios=["moon_base"])


def test_trainer_runs_resumes_and_reports(tmp_path):
    """Two iterations on tiny frames, then a resume to three: loss.csv continues, the plot, the checkpoint and the
    evaluation (per-class PQ) are written."""
    cfg = dict(scenarios=["indoor_handheld"], train_seeds=[1], val_seeds=[100], frames_per_sequence=2,
               val_frames_per_sequence=1, width=64, height=48, batch_size=1, crop=None, warmup=1,
               checkpoint_every=1, progress=False, eval_min_gt_area=4)
    s1 = run(TrainConfig(iterations=2, **cfg), tmp_path, resume=False)
    assert s1["iterations"] == 2 and s1["stopped_by"] == "iterations"
    s2 = run(TrainConfig(iterations=3, **cfg), tmp_path, resume=True)
    assert s2["iterations"] == 3
    rows = list(csv.DictReader((tmp_path / "loss.csv").open()))
    assert [int(r["iteration"]) for r in rows] == [1, 2, 3]
    for name in ("loss.png", "last.pt", "model_final.pth", "eval.md"):
        assert (tmp_path / name).is_file(), name
    ev = json.loads((tmp_path / "eval.json").read_text())
    assert ev["num_frames"] == 1 and {"things", "stuff", "per_category"} <= set(ev["pq"])
    names = {c["name"] for c in ev["pq"]["per_category"].values()}
    assert names == {c.name for c in synthetic_category_set().categories}
    assert 0.0 <= s2["pq"] <= 1.0


def test_two_trainings_sharing_a_cache_do_not_collide(tmp_path, monkeypatch):
    """Two runs that render the same sequence into one ``data_cache`` at once: the other run writes and replaces the
    cached file between this run's write and its replace; this run must still finish (each writes a temporary file
    of its own) and the cache hold one file, no temporary left."""
    import numpy as np

    from pvslam_plugins.segmenters.panoptic_fpn import data

    real_save = np.savez_compressed
    other_run_done = []

    def save_then_the_other_run_caches_too(*args, **kwargs):
        real_save(*args, **kwargs)
        if not other_run_done:
            other_run_done.append(True)
            data.load_samples(tmp_path / "cache", "driving_loop", 3, 2, 64, 48)

    monkeypatch.setattr(data.np, "savez_compressed", save_then_the_other_run_caches_too)
    mine = data.load_samples(tmp_path / "cache", "driving_loop", 3, 2, 64, 48)
    cached = data.load_samples(tmp_path / "cache", "driving_loop", 3, 2, 64, 48)
    assert other_run_done and len(mine) == len(cached) == 2
    assert all(torch.equal(a.image, b.image) and torch.equal(a.ids, b.ids) for a, b in zip(mine, cached))
    assert [f.name for f in (tmp_path / "cache").iterdir()] == ["driving_loop-seed3-n2-64x48.npz"]


def test_frames_hold_int32_ids_and_train_as_int64_ones_would(tmp_path):
    """Every training frame stays in memory: ids are int32 (half of int64), rendered or cached, and the augmentation
    gives the same labels from them as from int64 ids."""
    from pvslam_plugins.segmenters.panoptic_fpn import data

    fresh = data.load_samples(tmp_path, "moving_vehicles", 5, 2, 64, 48)
    cached = data.load_samples(tmp_path, "moving_vehicles", 5, 2, 64, 48)
    assert all(s.ids.dtype == torch.int32 for s in fresh + cached) and (fresh[0].ids // 1000 == 11).any()
    aug = Augment(scale=(0.7, 1.3), crop=(32, 40))
    for seed in range(4):
        a = aug(fresh[0].image, fresh[0].ids, torch.Generator().manual_seed(seed))
        b = aug(fresh[0].image, fresh[0].ids.long(), torch.Generator().manual_seed(seed))
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]) and a[1].dtype == torch.int64
