"""NMS, batched NMS, ROIAlign, box decoding, anchors and ROI level assignment against references written here
(Python loops over boxes / bins / samples, following the definitions in reference/checkpoints.md §2.6-2.7)."""
from __future__ import annotations

import math

import pytest
import torch

from pvslam_plugins.segmenters.panoptic_fpn.ops import (
    SCALE_CLAMP,
    apply_deltas,
    batched_nms,
    clip_boxes,
    nms,
    nonempty,
    roi_align,
    roi_align_fixed,
)
from pvslam_plugins.segmenters.panoptic_fpn.roi_heads import assign_levels
from pvslam_plugins.segmenters.panoptic_fpn.rpn import cell_anchors, grid_anchors

from _refs import nms_ref, roi_align_ref


# ------------------------------------------------------------------------------------------------- references
def batched_nms_ref(boxes, scores, idxs, thr) -> list[int]:
    keep = []
    for g in sorted(set(idxs.tolist())):
        where = [i for i, v in enumerate(idxs.tolist()) if v == g]
        keep += [where[k] for k in nms_ref(boxes[where], scores[where], thr)]
    return sorted(keep, key=lambda i: -float(scores[i]))


def clustered_boxes(n: int, seed: int, extent: float = 100.0) -> torch.Tensor:
    """Boxes around a few centres, so that many pairs overlap at every IoU level."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(max(1, n // 8), 2, generator=g) * extent
    pick = torch.randint(0, centres.shape[0], (n,), generator=g)
    ctr = centres[pick] + torch.randn(n, 2, generator=g) * 4
    wh = torch.rand(n, 2, generator=g) * 30 + 2
    return torch.cat([ctr - wh / 2, ctr + wh / 2], dim=1)


# ------------------------------------------------------------------------------------------------------- NMS
@pytest.mark.parametrize("seed,n,thr", [(0, 60, 0.5), (1, 200, 0.7), (2, 150, 0.3), (3, 1, 0.5)])
def test_nms_matches_greedy_reference(seed, n, thr):
    boxes = clustered_boxes(n, seed)
    scores = torch.rand(n, generator=torch.Generator().manual_seed(seed + 100))
    keep = nms(boxes, scores, thr)
    assert keep.tolist() == nms_ref(boxes, scores, thr)
    assert nms(boxes, scores, thr, block=7).tolist() == keep.tolist()  # many blocks, decisions across blocks
    assert len(keep) < n or n == 1  # the clusters do overlap


def test_nms_iou_equal_to_threshold_is_kept():
    boxes = torch.tensor([[0.0, 0.0, 10.0, 10.0], [0.0, 0.0, 10.0, 5.0], [0.0, 0.0, 10.0, 4.0]])
    scores = torch.tensor([0.9, 0.8, 0.7])
    # IoU(0,1) = 0.5 exactly: not suppressed (strictly greater); IoU(0,2) = 0.4, IoU(1,2) = 0.8 -> 2 suppressed by 1
    assert nms(boxes, scores, 0.5).tolist() == [0, 1]
    assert nms(boxes, scores, 0.49).tolist() == [0, 2]


def test_nms_chain_needs_propagation():
    # a suppression chain: 0 kills 1, so 2 (overlapping only 1) survives; 3 overlaps only 2 and is killed
    boxes = torch.tensor([[0.0, 0, 10, 10], [2.0, 0, 12, 10], [4.0, 0, 14, 10], [6.0, 0, 16, 10]])
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6])
    assert nms(boxes, scores, 0.6).tolist() == nms_ref(boxes, scores, 0.6) == [0, 2]


@pytest.mark.parametrize("n", [80, 1500])  # coordinate-trick path and per-group path
def test_batched_nms_matches_per_class_reference(n):
    boxes = clustered_boxes(n, 5, extent=60.0)
    g = torch.Generator().manual_seed(6)
    scores = torch.rand(n, generator=g)
    idxs = torch.randint(0, 4, (n,), generator=g)
    keep = batched_nms(boxes, scores, idxs, 0.5)
    assert keep.tolist() == batched_nms_ref(boxes, scores, idxs, 0.5)
    # boxes of different classes never suppress each other
    assert set(idxs[keep].tolist()) == set(idxs.tolist())


def test_batched_nms_empty():
    assert batched_nms(torch.zeros(0, 4), torch.zeros(0), torch.zeros(0, dtype=torch.int64), 0.5).numel() == 0


# -------------------------------------------------------------------------------------------------- ROIAlign
def _rois() -> torch.Tensor:
    # (batch, x0, y0, x1, y1) in image pixels: typical, tiny, partly outside, far outside, thin, large, degenerate
    return torch.tensor([
        [0, 3.3, 4.1, 20.7, 17.9],
        [1, 10.0, 10.0, 11.0, 11.5],
        [0, -6.0, -3.0, 9.0, 12.0],
        [1, 30.0, 28.0, 50.0, 44.0],
        [0, 0.5, 12.0, 35.0, 14.0],
        [1, 0.0, 0.0, 36.0, 36.0],
        [0, 12.0, 12.0, 12.0, 12.0],
        [1, 8.0, 9.0, 6.0, 20.0],
    ])


@pytest.mark.parametrize("sampling_ratio", [0, 2])
@pytest.mark.parametrize("aligned", [True, False])
def test_roi_align_matches_reference(sampling_ratio, aligned):
    g = torch.Generator().manual_seed(0)
    feat = torch.randn(2, 3, 9, 10, generator=g)  # stride 4 -> a 36x40 image
    rois = _rois()
    got = roi_align(feat, rois, 5, 0.25, sampling_ratio, aligned)
    ref = roi_align_ref(feat, rois, 5, 0.25, sampling_ratio, aligned)
    assert got.shape == (8, 3, 5, 5)
    assert torch.allclose(got.double(), ref, atol=1e-5, rtol=0), (got.double() - ref).abs().max()


@pytest.mark.parametrize("aligned", [True, False])
def test_roi_align_fixed_matches_reference(aligned):
    """The batched fixed-sub-grid path (reduced preset, training): same bins as the kernel, in float32 to 1e-5;
    images with different ROI counts (the padding slots must not leak) and an image without ROIs."""
    g = torch.Generator().manual_seed(0)
    feat = torch.randn(3, 3, 9, 10, generator=g)
    rois = torch.cat([_rois(), torch.tensor([[1, 2.0, 3.0, 30.0, 20.0], [1, 5.5, 1.0, 9.0, 33.0]])])
    for sr in (1, 2, 3):
        got = roi_align_fixed(feat, rois, (5, 4), 0.25, sr, aligned)
        ref = roi_align_ref(feat, rois, (5, 4), 0.25, sr, aligned)
        assert got.shape == (10, 3, 5, 4) and got.dtype == torch.float32
        assert torch.allclose(got.double(), ref, atol=1e-5, rtol=0), (got.double() - ref).abs().max()
    assert roi_align_fixed(feat, rois[:0], 5, 0.25, 2).shape == (0, 3, 5, 5)
    with pytest.raises(ValueError, match="sampling_ratio > 0"):
        roi_align_fixed(feat, rois, 5, 0.25, 0)


def test_roi_align_adaptive_grid_large_rois_and_chunks():
    """ROIs needing 1..6 samples per bin and axis, processed in several chunks of mixed sub-grids."""
    g = torch.Generator().manual_seed(1)
    feat = torch.randn(1, 4, 16, 16, generator=g)
    x0 = torch.rand(12, generator=g) * 10
    y0 = torch.rand(12, generator=g) * 10
    size = torch.linspace(2, 60, 12)
    rois = torch.stack([torch.zeros(12), x0, y0, x0 + size, y0 + size * 0.7], dim=1)
    got = roi_align(feat, rois, 3, 0.5, 0, True, max_chunk_elements=3 * 3 * 49 * 4 * 2)
    ref = roi_align_ref(feat, rois, 3, 0.5, 0, True)
    assert torch.allclose(got.double(), ref, atol=1e-5, rtol=0)


def test_roi_align_exact_on_a_large_map():
    """p2 of a 1333x800 input: coordinates in the hundreds, where float32 grid coordinates would drift."""
    g = torch.Generator().manual_seed(2)
    feat = torch.randn(1, 2, 200, 333, generator=g)
    x0, y0 = 900 + torch.rand(4, generator=g) * 300, 500 + torch.rand(4, generator=g) * 250
    rois = torch.stack([torch.zeros(4), x0, y0, x0 + 20 + torch.rand(4, generator=g) * 30,
                        y0 + 15 + torch.rand(4, generator=g) * 30], dim=1)
    got = roi_align(feat, rois, 4, 0.25, 0, True)
    # 1e-6, tighter than the 1e-5 target: float32 grid_sample coordinates are off by 8e-6 here
    assert torch.allclose(got.double(), roi_align_ref(feat, rois, 4, 0.25, 0, True), atol=1e-6, rtol=0)


def test_roi_align_gradient_flows_to_features():
    feat = torch.randn(1, 2, 8, 8, requires_grad=True)
    out = roi_align(feat, torch.tensor([[0, 4.0, 4.0, 20.0, 24.0]]), 2, 0.25, 0, True)
    out.sum().backward()
    assert feat.grad is not None and feat.grad.abs().sum() > 0
    # every output is an average of samples, i.e. a convex combination of feature values: weights sum to 1
    assert torch.allclose(feat.grad.sum(), torch.tensor(2 * 4.0))


# ----------------------------------------------------------------------------------------------- box coding
def test_apply_deltas_hand_computed():
    boxes = torch.tensor([[10.0, 20.0, 30.0, 60.0]])  # w 20, h 40, centre (20, 40)
    deltas = torch.tensor([[1.0, -0.5, math.log(2.0), 0.0]])
    out = apply_deltas(deltas, boxes, (1.0, 1.0, 1.0, 1.0))
    # centre (20 + 20, 40 - 20) = (40, 20); size (40, 40)
    assert torch.allclose(out, torch.tensor([[20.0, 0.0, 60.0, 40.0]]))
    # ROI-head weights (10, 10, 5, 5): deltas are divided first
    out = apply_deltas(torch.tensor([[10.0, -5.0, 5 * math.log(2.0), 0.0]]), boxes, (10.0, 10.0, 5.0, 5.0))
    assert torch.allclose(out, torch.tensor([[20.0, 0.0, 60.0, 40.0]]))


def test_apply_deltas_clamps_scale_and_is_class_specific():
    boxes = torch.tensor([[0.0, 0.0, 16.0, 16.0]])
    deltas = torch.tensor([[0.0, 0.0, 100.0, 100.0, 0.0, 0.0, 0.0, 0.0]])  # two classes
    out = apply_deltas(deltas, boxes)
    assert out.shape == (1, 8)
    side = 16 * math.exp(SCALE_CLAMP)  # = 1000
    assert torch.allclose(out[0, :4], torch.tensor([8 - side / 2, 8 - side / 2, 8 + side / 2, 8 + side / 2]))
    assert torch.allclose(out[0, 4:], boxes[0])


def test_clip_and_nonempty():
    b = torch.tensor([[-5.0, -1.0, 50.0, 8.0], [20.0, 3.0, 20.0, 9.0], [39.0, 9.0, 45.0, 12.0]])
    c = clip_boxes(b, (10, 40))
    assert c.tolist() == [[0.0, 0.0, 40.0, 8.0], [20.0, 3.0, 20.0, 9.0], [39.0, 9.0, 40.0, 10.0]]
    assert nonempty(c).tolist() == [True, False, True]


# --------------------------------------------------------------------------------------------------- anchors
def test_cell_anchors_hand_computed():
    a = cell_anchors([32], [0.5, 1.0, 2.0])
    # ratio = h / w, area 32^2: w = 32 / sqrt(ratio)
    w05, w2 = 32 / math.sqrt(0.5), 32 / math.sqrt(2.0)
    expected = [[-w05 / 2, -w05 * 0.5 / 2, w05 / 2, w05 * 0.5 / 2], [-16, -16, 16, 16],
                [-w2 / 2, -w2 * 2 / 2, w2 / 2, w2 * 2 / 2]]
    assert torch.allclose(a, torch.tensor(expected), atol=1e-5)
    # size-major order
    two = cell_anchors([32, 64], [1.0, 2.0])
    assert torch.allclose(two[1, 2] - two[1, 0], torch.tensor(32 / math.sqrt(2.0)))
    assert torch.allclose(two[2], torch.tensor([-32.0, -32.0, 32.0, 32.0]))


def test_grid_anchors_order_is_h_w_a():
    cell = cell_anchors([16], [0.5, 1.0, 2.0])
    stride, h, w = 8, 3, 4
    got = grid_anchors(cell, (h, w), stride, offset=0.0)
    ref = []
    for y in range(h):
        for x in range(w):
            for a in range(3):
                cx, cy = x * stride, y * stride
                ref.append([cx + cell[a, 0].item(), cy + cell[a, 1].item(), cx + cell[a, 2].item(),
                            cy + cell[a, 3].item()])
    assert torch.allclose(got, torch.tensor(ref))
    half = grid_anchors(cell, (h, w), stride, offset=0.5)
    assert torch.allclose(half - got, torch.full_like(got, 4.0))


# ----------------------------------------------------------------------------------------- level assignment
def test_assign_levels_canonical_224_at_level_4():
    def box(side):
        return [0.0, 0.0, float(side), float(side)]

    boxes = torch.tensor([box(224), box(223.9), box(112), box(111.9), box(448), box(10), box(5000),
                          [0.0, 0.0, 448.0, 112.0]])  # sqrt(area) = 224
    lv = assign_levels(boxes, 2, 5) + 2
    # floor(4 + log2(s/224 + 1e-8)), clamped to [2, 5]
    ref = [min(5, max(2, math.floor(4 + math.log2(math.sqrt((b[2] - b[0]) * (b[3] - b[1])) / 224 + 1e-8))))
           for b in boxes.tolist()]
    assert lv.tolist() == ref == [4, 3, 3, 2, 5, 2, 5, 4]
