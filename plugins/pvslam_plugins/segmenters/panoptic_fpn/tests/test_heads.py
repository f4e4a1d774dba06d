"""Frozen BN, RPN proposal selection, box-head selection, mask pasting and the panoptic combine against references
written here (Python loops) from their definitions (reference/checkpoints.md §2.4-2.8)."""
from __future__ import annotations

import math

import pytest
import torch

from pvslam_plugins.segmenters.panoptic_fpn.config import BoxHeadConfig, MaskHeadConfig, RPNConfig
from pvslam_plugins.segmenters.panoptic_fpn.layers import FrozenBatchNorm2d
from pvslam_plugins.segmenters.panoptic_fpn.model import resized_shape
from pvslam_plugins.segmenters.panoptic_fpn.panoptic import argmax_channels, combine
from pvslam_plugins.segmenters.panoptic_fpn.roi_heads import ROIHeads, paste_masks
from pvslam_plugins.segmenters.panoptic_fpn.rpn import RPN

from _refs import nms_ref


def test_frozen_bn_equals_formula():
    bn = FrozenBatchNorm2d(4)
    g = torch.Generator().manual_seed(0)
    bn.weight.copy_(torch.randn(4, generator=g))
    bn.bias.copy_(torch.randn(4, generator=g))
    bn.running_mean.copy_(torch.randn(4, generator=g))
    bn.running_var.copy_(torch.rand(4, generator=g) + 0.1)
    x = torch.randn(2, 4, 3, 5, generator=g)
    ref = torch.empty_like(x)
    for c in range(4):
        ref[:, c] = (x[:, c] - bn.running_mean[c]) / math.sqrt(bn.running_var[c] + 1e-5) * bn.weight[c] + bn.bias[c]
    assert torch.allclose(bn(x), ref, atol=1e-5)
    assert sorted(bn.state_dict()) == ["bias", "running_mean", "running_var", "weight"]
    assert not list(bn.parameters())  # nothing trains
    fresh = FrozenBatchNorm2d(3)
    assert torch.allclose(fresh(x[:, :3]), x[:, :3], atol=1e-6)  # identity at init (running_var = 1 - eps)


def test_resized_shape_detectron2_policy():
    assert resized_shape(480, 640, 800, 1333) == (800, 1067)  # 640 * 800 / 480 = 1066.67 -> int(x + .5)
    assert resized_shape(370, 1226, 800, 1333) == (402, 1333)  # capped by the longer side
    assert resized_shape(375, 1242, 375, 1242) == (375, 1242)  # PVO's VKITTI2 setting is the identity
    assert resized_shape(240, 320, 0, 1333) == (240, 320)  # 0 = no resize
    assert resized_shape(640, 480, 800, 1333) == (1067, 800)


# ------------------------------------------------------------------------------------------------ RPN select
def test_rpn_select_matches_reference():
    cfg = RPNConfig(pre_nms_topk_test=6, post_nms_topk_test=7, nms_thresh=0.6)
    rpn = RPN(cfg, 8, [4, 8, 16, 32, 64]).eval()
    g = torch.Generator().manual_seed(3)
    feats = [torch.randn(1, 8, s, s + 1, generator=g) for s in (8, 4, 2, 1, 1)]
    size = (30, 34)
    anchors = rpn.anchors(feats)
    logits, deltas = rpn.head_outputs(feats)
    logits = [torch.randn(lg.shape, generator=g) for lg in logits]
    deltas = [torch.randn(d.shape, generator=g) * 0.3 for d in deltas]
    got = rpn.select(anchors, logits, deltas, [size])[0]
    # reference: per level, sort all anchors by logit, keep 6, decode by hand, clip, drop empty, NMS per level,
    # merge by score, keep 7
    cand = []
    for lvl, (a, lg, d) in enumerate(zip(anchors, logits, deltas)):
        order = sorted(range(lg.shape[1]), key=lambda i: -float(lg[0, i]))[:6]
        for i in order:
            x0, y0, x1, y1 = a[i].tolist()
            dx, dy, dw, dh = d[0, i].tolist()
            w, h = x1 - x0, y1 - y0
            cx, cy = x0 + 0.5 * w + dx * w, y0 + 0.5 * h + dy * h
            pw, ph = math.exp(min(dw, math.log(1000 / 16))) * w, math.exp(min(dh, math.log(1000 / 16))) * h
            b = [min(max(cx - pw / 2, 0), size[1]), min(max(cy - ph / 2, 0), size[0]),
                 min(max(cx + pw / 2, 0), size[1]), min(max(cy + ph / 2, 0), size[0])]
            if b[2] - b[0] > 0 and b[3] - b[1] > 0:
                cand.append((float(lg[0, i]), lvl, b))
    kept = []
    for lvl in range(5):
        c = [x for x in cand if x[1] == lvl]
        boxes = torch.tensor([x[2] for x in c]).reshape(-1, 4)
        kept += [c[k] for k in nms_ref(boxes, torch.tensor([x[0] for x in c]), 0.6)]
    kept = sorted(kept, key=lambda x: -x[0])[:7]
    assert len(got.boxes) == len(kept) == 7
    assert torch.allclose(got.logits, torch.tensor([x[0] for x in kept]))
    assert torch.allclose(got.boxes, torch.tensor([x[2] for x in kept]), atol=1e-4)


# ------------------------------------------------------------------------------------------- box selection
def test_box_selection_matches_reference():
    heads = ROIHeads(BoxHeadConfig(num_classes=3, score_thresh_test=0.2, nms_thresh_test=0.5,
                                   detections_per_image=4), MaskHeadConfig(), 8, [4, 8, 16, 32])
    g = torch.Generator().manual_seed(4)
    r, k = 12, 3
    ctr = torch.rand(r, 2, generator=g) * 30 + 5
    boxes = torch.cat([ctr - 6, ctr + 6], 1).repeat(1, k) + torch.randn(r, 4 * k, generator=g)
    scores = torch.softmax(torch.randn(r, k + 1, generator=g) * 2, dim=1)
    size = (40, 44)
    got = heads.select_boxes(boxes, scores, size)
    cand = []  # (score, class, clipped box), row-major over (proposal, class)
    for i in range(r):
        for c in range(k):
            s = float(scores[i, c])
            if s > 0.2:
                b = boxes[i, 4 * c: 4 * c + 4].tolist()
                b = [min(max(b[0], 0), 44), min(max(b[1], 0), 40), min(max(b[2], 0), 44), min(max(b[3], 0), 40)]
                cand.append((s, c, b))
    kept = []
    for c in range(k):
        cc = [x for x in cand if x[1] == c]
        if cc:
            kept += [cc[j] for j in nms_ref(torch.tensor([x[2] for x in cc]), torch.tensor([x[0] for x in cc]), 0.5)]
    kept = sorted(kept, key=lambda x: -x[0])[:4]
    assert got.scores.tolist() == pytest.approx([x[0] for x in kept])
    assert got.classes.tolist() == [x[1] for x in kept]
    assert torch.allclose(got.boxes, torch.tensor([x[2] for x in kept]))


# ------------------------------------------------------------------------------------------------ mask paste
def paste_ref(m: torch.Tensor, box, h: int, w: int, thr: float) -> torch.Tensor:
    """grid_sample(align_corners=False, zeros padding) of one M x M mask at every pixel centre, by hand."""
    mm = m.shape[0]
    x0, y0, x1, y1 = box

    def at(i, j):
        return float(m[i, j]) if 0 <= i < mm and 0 <= j < mm else 0.0

    out = torch.zeros(h, w, dtype=torch.bool)
    for y in range(h):
        for x in range(w):
            u = ((x + 0.5) - x0) / (x1 - x0) * 2 - 1
            v = ((y + 0.5) - y0) / (y1 - y0) * 2 - 1
            ix, iy = ((u + 1) * mm - 1) / 2, ((v + 1) * mm - 1) / 2
            jx, jy = math.floor(ix), math.floor(iy)
            fx, fy = ix - jx, iy - jy
            val = ((1 - fy) * (1 - fx) * at(jy, jx) + (1 - fy) * fx * at(jy, jx + 1)
                   + fy * (1 - fx) * at(jy + 1, jx) + fy * fx * at(jy + 1, jx + 1))
            out[y, x] = val >= thr
    return out


def test_paste_masks_matches_reference():
    g = torch.Generator().manual_seed(5)
    probs = torch.rand(3, 6, 6, generator=g)
    probs[0] = 0.97  # a full mask: pasted inside the box only, and everywhere but the outermost half mask pixel
    boxes = torch.tensor([[2.3, 1.7, 11.2, 9.6], [-3.0, 4.0, 8.0, 30.0], [14.5, 0.0, 26.0, 5.5]])
    got = paste_masks(probs, boxes, (18, 22), 0.5)
    for i in range(3):
        assert torch.equal(got[i], paste_ref(probs[i], boxes[i].tolist(), 18, 22, 0.5)), i
    xs = torch.arange(22) + 0.5
    ys = torch.arange(18) + 0.5
    inside = (ys[:, None] > 1.7) & (ys[:, None] < 9.6) & (xs[None] > 2.3) & (xs[None] < 11.2)
    half_x, half_y = 8.9 / 12, 7.9 / 12  # half a mask pixel in image pixels
    core = ((ys[:, None] > 1.7 + half_y) & (ys[:, None] < 9.6 - half_y) & (xs[None] > 2.3 + half_x)
            & (xs[None] < 11.2 - half_x))
    assert not (got[0] & ~inside).any() and (got[0] | ~core).all() and core.sum() > 20


# -------------------------------------------------------------------------------------------------- combine
def combine_ref(masks, scores, classes, sem, overlap, stuff_area, conf):
    """detectron2 combine_semantic_and_instance_outputs, pixel by pixel."""
    n, h, w = masks.shape
    pan = [[0] * w for _ in range(h)]
    segs = []
    for i in sorted(range(n), key=lambda i: -float(scores[i])):
        if float(scores[i]) < conf:
            break
        pix = [(y, x) for y in range(h) for x in range(w) if masks[i, y, x]]
        if not pix:
            continue
        inter = sum(1 for y, x in pix if pan[y][x] > 0)
        if inter / len(pix) > overlap:
            continue
        sid = len(segs) + 1
        for y, x in pix:
            if pan[y][x] == 0:
                pan[y][x] = sid
        segs.append((True, int(classes[i])))
    for lab in sorted(set(sem.flatten().tolist())):
        if lab == 0:
            continue
        pix = [(y, x) for y in range(h) for x in range(w) if sem[y, x] == lab and pan[y][x] == 0]
        if len(pix) < stuff_area:
            continue
        sid = len(segs) + 1
        for y, x in pix:
            pan[y][x] = sid
        segs.append((False, lab))
    return torch.tensor(pan), segs


def test_combine_matches_reference():
    h, w = 12, 14
    masks = torch.zeros(5, h, w, dtype=torch.bool)
    masks[0, 2:8, 2:8] = True  # score 0.9
    masks[1, 4:10, 4:10] = True  # 0.8: overlaps 0 by 16/36 < 0.5 -> keeps its free pixels
    masks[2, 2:7, 3:8] = True  # 0.7: mostly covered (> 0.5) -> dropped
    masks[3, 0:2, 10:14] = True  # 0.4: below the confidence threshold -> loop stops
    # 4: empty mask with a high score -> skipped
    scores = torch.tensor([0.9, 0.8, 0.7, 0.4, 0.95])
    classes = torch.tensor([2, 0, 1, 1, 2])
    sem = torch.zeros(h, w, dtype=torch.int64)
    sem[:, :7] = 3
    sem[:, 7:] = 5
    sem[10:, :] = 1  # label 1: 28 px, partly free
    sem[0, 0] = 7  # a 1-pixel label: below the stuff area limit
    got = combine(masks, scores, classes, sem, 0.5, 10, 0.5)
    ids, segs = combine_ref(masks, scores, classes, sem, 0.5, 10, 0.5)
    assert torch.equal(got.ids, ids)
    assert list(zip(got.isthing, got.labels)) == segs
    # with boxes (masks empty outside box + 1 px) the work is windowed; the result must not change
    boxes = torch.tensor([[2.0, 2.0, 8.0, 8.0], [4.5, 4.2, 9.5, 9.9], [3.0, 2.0, 8.0, 7.0], [10.0, 0.0, 14.0, 2.0],
                          [0.0, 0.0, 1.0, 1.0]])
    windowed = combine(masks, scores, classes, sem, 0.5, 10, 0.5, boxes=boxes)
    assert torch.equal(windowed.ids, ids) and windowed.areas == got.areas
    assert segs[:2] == [(True, 2), (True, 0)] and [s for s in segs if not s[0]] == [(False, 1), (False, 3), (False, 5)]
    assert got.instances[:2] == [0, 1]
    assert got.areas[1] == 36 - 16


def test_combine_stuff_scores_and_empty_inputs():
    sem = torch.tensor([[1, 1], [2, 0]])
    label_probs = torch.tensor([[0.6, 0.8], [0.9, 0.3]])  # probability of each pixel's argmax label
    got = combine(torch.zeros(0, 2, 2, dtype=torch.bool), torch.zeros(0), torch.zeros(0, dtype=torch.int64), sem,
                  stuff_area_limit=1, label_probs=label_probs)
    assert got.ids.tolist() == [[1, 1], [2, 0]]
    assert got.scores == pytest.approx([0.7, 0.9])
    assert got.areas == [2, 1] and got.labels == [1, 2] and got.instances == [-1, -1]


def test_argmax_channels_equals_argmax_and_softmax():
    g = torch.Generator().manual_seed(7)
    logits = torch.randn(6, 9, 11, generator=g) * 3
    logits[:, 0, 0] = 2.0  # a tie: the lowest channel wins, as torch.argmax
    label, prob = argmax_channels(logits[:, :8, :10])  # a non-contiguous view, as the cropped padded logits
    assert torch.equal(label, logits[:, :8, :10].argmax(0))
    assert torch.allclose(prob, logits[:, :8, :10].softmax(0).max(0).values, atol=1e-6)
