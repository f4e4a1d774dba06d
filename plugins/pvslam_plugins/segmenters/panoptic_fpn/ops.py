"""Box operators of PanopticFPN in plain, vectorised torch: IoU, NMS (batched by class), ROIAlign, box decoding.

Each follows the definition detectron2 / torchvision use (reference/checkpoints.md §2.6-2.7), so a converted
model-zoo checkpoint gives the same detections:

* boxes are ``[x0, y0, x1, y1]`` in pixels, width = x1 - x0 (no +1);
* NMS drops a box whose IoU with a kept, higher-scoring box is **strictly greater** than the threshold;
  scores are ordered with a stable descending sort;
* ROIAlign samples bilinearly exactly as torchvision's ``roi_align`` kernel (``aligned`` shifts by half a pixel;
  ``sampling_ratio <= 0`` = adaptive ``ceil(roi_size / output_size)`` samples per bin and axis, per ROI).
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F

#: detectron2's _DEFAULT_SCALE_CLAMP: exp(dw) is capped so a box grows at most 1000/16 times per decoding
SCALE_CLAMP = math.log(1000.0 / 16)

__all__ = [
    "SCALE_CLAMP",
    "box_area",
    "box_iou",
    "nms",
    "batched_nms",
    "roi_align",
    "roi_align_fixed",
    "apply_deltas",
    "clip_boxes",
    "nonempty",
]


def box_area(boxes: torch.Tensor) -> torch.Tensor:
    """``[N, 4] -> [N]``: (x1 - x0) * (y1 - y0)."""
    return (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise IoU ``[N, 4] x [M, 4] -> [N, M]`` (torchvision's formula: inter / (area_a + area_b - inter))."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    wh = (rb - lt).clamp(min=0)
    inter = wh[..., 0] * wh[..., 1]
    return inter / (box_area(a)[:, None] + box_area(b)[None, :] - inter)


def _suppression_edges(boxes: torch.Tensor, iou_threshold: float, chunk: int = 1024) -> torch.Tensor:
    """Boolean ``[N, N]``: ``S[i, j]`` = box i (earlier in score order) overlaps box j (later) above threshold.

    Computed in row chunks so the float IoU never needs more than ``chunk x N`` memory."""
    n = boxes.shape[0]
    s = torch.zeros((n, n), dtype=torch.bool, device=boxes.device)
    cols = torch.arange(n, device=boxes.device)
    for start in range(0, n, chunk):
        rows = torch.arange(start, min(start + chunk, n), device=boxes.device)
        s[rows] = (box_iou(boxes[rows], boxes) > iou_threshold) & (cols[None, :] > rows[:, None])
    return s


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float, block: int = 128) -> torch.Tensor:
    """Greedy non-maximum suppression; returns int64 indices of the kept boxes, by decreasing score.

    Greedy NMS keeps box j iff no *kept* higher-scoring box overlaps it: ``keep = not (S^T keep)`` with ``S`` the
    strictly-upper-triangular overlap matrix in score order.  That equation has exactly one solution (by induction
    over the score order).  Boxes are decided in blocks of ``block`` in score order: the boxes kept in earlier
    blocks strike out what they overlap (one mat-vec), then the block's own equation is iterated from "keep all
    candidates" until it stops changing -- each round settles at least the next undecided box, so a block needs
    at most ``block`` rounds and real boxes a handful, instead of one Python iteration per box.
    """
    n = int(boxes.shape[0])
    if n == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    order = torch.sort(scores, descending=True, stable=True).indices
    s = _suppression_edges(boxes[order].float(), iou_threshold).to(torch.float32)  # s[i, j]: i suppresses j
    keep = torch.zeros(n, dtype=torch.float32, device=boxes.device)
    for start in range(0, n, block):
        end = min(start + block, n)
        cand = keep[:start] @ s[:start, start:end] == 0 if start else torch.ones(
            end - start, dtype=torch.bool, device=boxes.device)
        st = s[start:end, start:end].t()  # st[j, i] = i suppresses j
        k = cand.to(torch.float32)
        for _ in range(end - start + 1):
            new = (cand & (st @ k == 0)).to(torch.float32)
            if torch.equal(new, k):
                break
            k = new
        keep[start:end] = k
    return order[keep.bool()]


def batched_nms(
    boxes: torch.Tensor, scores: torch.Tensor, idxs: torch.Tensor, iou_threshold: float
) -> torch.Tensor:
    """NMS done independently per value of ``idxs`` (class or FPN level), as torchvision's ``batched_nms``.

    Like torchvision on the CPU: up to 1000 boxes, one NMS on boxes offset by ``idx * (max_coordinate + 1)`` so
    that boxes of different groups never overlap ("coordinate trick"); above that, one NMS per group (less
    memory than one N x N matrix).  Both keep the same boxes.  Returns indices sorted by decreasing score.
    """
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    if boxes.numel() <= 4000:
        max_coordinate = boxes.max()
        offsets = idxs.to(boxes) * (max_coordinate + torch.tensor(1, dtype=boxes.dtype, device=boxes.device))
        return nms(boxes + offsets[:, None], scores, iou_threshold)
    keep_mask = torch.zeros_like(scores, dtype=torch.bool)
    for group in torch.unique(idxs).tolist():
        where = torch.nonzero(idxs == group).squeeze(1)
        keep_mask[where[nms(boxes[where], scores[where], iou_threshold)]] = True
    keep = torch.nonzero(keep_mask).squeeze(1)
    return keep[torch.sort(scores[keep], descending=True, stable=True).indices]


# --------------------------------------------------------------------------------------------------- ROIAlign
def roi_align(
    features: torch.Tensor,
    rois: torch.Tensor,
    output_size: int | Sequence[int],
    spatial_scale: float,
    sampling_ratio: int = 0,
    aligned: bool = True,
    max_chunk_elements: int = 1 << 24,
) -> torch.Tensor:
    """ROIAlign of ``features [B, C, H, W]`` over ``rois [R, 5]`` = (batch index, x0, y0, x1, y1) in image pixels.

    Returns ``[R, C, ph, pw]``.  Semantics of torchvision.ops.roi_align (and detectron2's ROIAlign / ROIAlignV2):
    the ROI is scaled by ``spatial_scale`` and, with ``aligned``, shifted by -0.5 px; each of the ``ph x pw`` bins
    averages ``gy x gx`` bilinear samples at the centres of a regular sub-grid, where ``g = sampling_ratio`` or,
    if that is <= 0, ``ceil(roi_size / bins)`` per ROI and axis.  A sample outside ``[-1, size]`` counts as 0;
    samples in ``[-1, 0)`` and ``(size - 1, size]`` take the border value.  Differentiable in ``features``.

    How: ``grid_sample`` with border padding is exactly that bilinear sample inside ``[-1, size]`` (it clamps the
    coordinate to the border); the "outside counts as 0" rule is a per-axis validity weight applied afterwards.
    ROIs are grouped by (image, gy, gx) so each group is one rectangular sampling grid with no padding.  Sample
    positions are computed in the features' dtype (as the kernel does) but sampled in float64: grid_sample's
    [-1, 1] coordinates would otherwise lose ~size * 6e-8 px (2e-5 px on a 300-px map).
    """
    ph, pw = (output_size, output_size) if isinstance(output_size, int) else tuple(output_size)
    b, c, h, w = features.shape
    r = int(rois.shape[0])
    out = features.new_zeros((r, c, ph, pw))
    if r == 0:
        return out
    rois = rois.to(features.dtype)
    offset = 0.5 if aligned else 0.0
    x0 = rois[:, 1] * spatial_scale - offset
    y0 = rois[:, 2] * spatial_scale - offset
    rw = rois[:, 3] * spatial_scale - offset - x0
    rh = rois[:, 4] * spatial_scale - offset - y0
    if not aligned:  # the legacy op forces malformed ROIs to 1x1
        rw, rh = rw.clamp(min=1.0), rh.clamp(min=1.0)
    bw, bh = rw / pw, rh / ph
    if sampling_ratio > 0:
        gx = torch.full((r,), sampling_ratio, dtype=torch.int64, device=rois.device)
        gy = gx
    else:  # ceil in the feature dtype, as the kernel does; a negative-size ROI gets no samples (output 0)
        gx = torch.ceil(rw / pw).to(torch.int64).clamp(min=0)
        gy = torch.ceil(rh / ph).to(torch.int64).clamp(min=0)
    bidx = rois[:, 0].to(torch.int64)
    gmax = int(torch.maximum(gx, gy).max()) + 1
    key = (bidx * gmax + gy) * gmax + gx
    uniq, inverse = torch.unique(key, return_inverse=True)
    maps: dict[int, torch.Tensor] = {}  # float64 copy of each image's map, made once
    for u, k in enumerate(uniq.tolist()):
        n_gx, n_gy, n_b = k % gmax, (k // gmax) % gmax, k // (gmax * gmax)
        if n_gx == 0 or n_gy == 0:
            continue
        sel = torch.nonzero(inverse == u).squeeze(1)
        step = max(1, max_chunk_elements // (c * ph * n_gy * pw * n_gx))
        if n_b not in maps:
            maps[n_b] = features[n_b:n_b + 1].double()
        for s in range(0, int(sel.numel()), step):
            idx = sel[s:s + step]
            out[idx] = _sample_bins(maps[n_b], x0[idx], y0[idx], bw[idx], bh[idx], ph, pw, n_gy, n_gx).to(out.dtype)
    return out


def _sample_bins(fm: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, bw: torch.Tensor, bh: torch.Tensor,
                 ph: int, pw: int, gy: int, gx: int) -> torch.Tensor:
    """Mean of ``gy x gx`` samples per bin for ``n`` ROIs on one map ``[1, C, H, W]`` -> ``[n, C, ph, pw]``."""
    _, c, h, w = fm.shape
    n = x0.shape[0]

    def axis(start, bin_size, bins, grid, size):
        p = torch.arange(bins, device=start.device, dtype=start.dtype)
        i = torch.arange(grid, device=start.device, dtype=start.dtype)
        # exactly the kernel's expression: start + p * bin + (i + .5) * bin / grid
        pos = start[:, None, None] + p[None, :, None] * bin_size[:, None, None] + \
            (i[None, None, :] + 0.5) * bin_size[:, None, None] / grid  # [n, bins, grid]
        weight = ((pos >= -1.0) & (pos <= size)).to(torch.float64) / grid
        pos = pos.double()
        return (2.0 * pos + 1.0) / size - 1.0, weight  # grid_sample's align_corners=False coordinates

    ny, wy = axis(y0, bh, ph, gy, h)
    nx, wx = axis(x0, bw, pw, gx, w)
    grid = torch.stack(torch.broadcast_tensors(nx.reshape(n, 1, pw * gx), ny.reshape(n, ph * gy, 1)), dim=-1)
    samples = F.grid_sample(fm, grid.reshape(1, n * ph * gy, pw * gx, 2), mode="bilinear",
                            padding_mode="border", align_corners=False)  # [1, C, n*ph*gy, pw*gx]
    if bool((wx > 0).all()) and bool((wy > 0).all()):
        # every sample inside (clipped boxes): each bin is the plain mean of its gy x gx block
        pooled = F.avg_pool2d(samples, (gy, gx)).view(c, n, ph * pw)
        return pooled.transpose(0, 1).contiguous().view(n, c, ph, pw)
    samples = samples.view(c, n, ph, gy, pw, gx)
    if gx > 1 or not bool((wx == 1).all()):
        samples = (samples * wx[None, :, None, None, :, :]).sum(-1)
    else:
        samples = samples[..., 0]
    samples = (samples * wy[None, :, :, :, None]).sum(3)  # [C, n, ph, pw]
    return samples.permute(1, 0, 2, 3)


def roi_align_fixed(
    features: torch.Tensor,
    rois: torch.Tensor,
    output_size: int | Sequence[int],
    spatial_scale: float,
    sampling_ratio: int,
    aligned: bool = True,
) -> torch.Tensor:
    """:func:`roi_align` for a fixed ``sampling_ratio > 0``, in the features' dtype, with one ``grid_sample`` call.

    With a fixed sub-grid every ROI has the same number of samples, so the ROIs of each image are stacked into one
    sampling grid (images with fewer ROIs padded) and the whole batch is sampled at once; the result equals
    :func:`roi_align`'s up to float32 rounding of the sample positions (the exact path samples in float64).  The
    training step and the reduced configuration use it: no per-image slices, no float64 copies of the maps."""
    if sampling_ratio <= 0:
        raise ValueError(f"roi_align_fixed needs sampling_ratio > 0, got {sampling_ratio} (use roi_align)")
    ph, pw = (output_size, output_size) if isinstance(output_size, int) else tuple(output_size)
    b, c, h, w = features.shape
    r = int(rois.shape[0])
    if r == 0:
        return features.new_zeros((0, c, ph, pw))
    g = int(sampling_ratio)
    rois = rois.to(features.dtype)
    offset = 0.5 if aligned else 0.0
    x0 = rois[:, 1] * spatial_scale - offset
    y0 = rois[:, 2] * spatial_scale - offset
    rw = rois[:, 3] * spatial_scale - offset - x0
    rh = rois[:, 4] * spatial_scale - offset - y0
    if not aligned:
        rw, rh = rw.clamp(min=1.0), rh.clamp(min=1.0)
    bw, bh = rw / pw, rh / ph

    def axis(start, bin_size, bins, size):
        p = torch.arange(bins, device=start.device, dtype=start.dtype)
        i = torch.arange(g, device=start.device, dtype=start.dtype)
        pos = start[:, None, None] + p[None, :, None] * bin_size[:, None, None] + \
            (i[None, None, :] + 0.5) * bin_size[:, None, None] / g  # [r, bins, g], the kernel's expression
        weight = ((pos >= -1.0) & (pos <= size)).to(features.dtype) / g
        return (2.0 * pos + 1.0) / size - 1.0, weight

    ny, wy = axis(y0, bh, ph, h)
    nx, wx = axis(x0, bw, pw, w)
    bidx = rois[:, 0].to(torch.int64)
    counts = torch.bincount(bidx, minlength=b)
    m = int(counts.max())
    order = torch.argsort(bidx, stable=True)
    first = torch.cumsum(counts, 0) - counts
    slot = torch.empty_like(bidx)
    slot[order] = torch.arange(r, device=bidx.device) - first[bidx[order]]
    grid = features.new_zeros((b, m, ph * g, pw * g, 2))
    grid[bidx, slot] = torch.stack(torch.broadcast_tensors(nx.reshape(r, 1, pw * g), ny.reshape(r, ph * g, 1)), -1)
    samples = F.grid_sample(features, grid.view(b, m * ph * g, pw * g, 2), mode="bilinear", padding_mode="border",
                            align_corners=False)  # [b, C, m*ph*g, pw*g]
    samples = samples.view(b, c, m, ph, g, pw, g).permute(0, 2, 1, 3, 4, 5, 6)[bidx, slot]  # [r, C, ph, g, pw, g]
    weight = wy[:, None, :, :, None, None] * wx[:, None, None, None, :, :]
    return (samples * weight).sum(dim=(3, 5))


# ---------------------------------------------------------------------------------------------- box coding
def apply_deltas(
    deltas: torch.Tensor,
    boxes: torch.Tensor,
    weights: Sequence[float] = (1.0, 1.0, 1.0, 1.0),
    scale_clamp: float = SCALE_CLAMP,
) -> torch.Tensor:
    """detectron2 Box2BoxTransform.apply_deltas: ``deltas [R, 4K]`` relative to ``boxes [R, 4]`` -> ``[R, 4K]``.

    ``dx, dy, dw, dh`` are divided by ``weights``; ``dw, dh`` are clamped at ``scale_clamp`` before ``exp``."""
    deltas = deltas.float()
    boxes = boxes.to(deltas.dtype)
    widths = boxes[:, 2] - boxes[:, 0]
    heights = boxes[:, 3] - boxes[:, 1]
    ctr_x = boxes[:, 0] + 0.5 * widths
    ctr_y = boxes[:, 1] + 0.5 * heights
    wx, wy, ww, wh = weights
    dx = deltas[:, 0::4] / wx
    dy = deltas[:, 1::4] / wy
    dw = (deltas[:, 2::4] / ww).clamp(max=scale_clamp)
    dh = (deltas[:, 3::4] / wh).clamp(max=scale_clamp)
    pred_ctr_x = dx * widths[:, None] + ctr_x[:, None]
    pred_ctr_y = dy * heights[:, None] + ctr_y[:, None]
    pred_w = torch.exp(dw) * widths[:, None]
    pred_h = torch.exp(dh) * heights[:, None]
    x0 = pred_ctr_x - 0.5 * pred_w
    y0 = pred_ctr_y - 0.5 * pred_h
    x1 = pred_ctr_x + 0.5 * pred_w
    y1 = pred_ctr_y + 0.5 * pred_h
    return torch.stack((x0, y0, x1, y1), dim=-1).reshape(deltas.shape)


def clip_boxes(boxes: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Clamp ``[..., 4]`` boxes to an image of ``size = (h, w)``: x in [0, w], y in [0, h]."""
    h, w = size
    x0 = boxes[..., 0].clamp(min=0, max=w)
    y0 = boxes[..., 1].clamp(min=0, max=h)
    x1 = boxes[..., 2].clamp(min=0, max=w)
    y1 = boxes[..., 3].clamp(min=0, max=h)
    return torch.stack((x0, y0, x1, y1), dim=-1)


def nonempty(boxes: torch.Tensor, threshold: float = 0.0) -> torch.Tensor:
    """``[N] bool``: width and height both strictly greater than ``threshold``."""
    return ((boxes[:, 2] - boxes[:, 0]) > threshold) & ((boxes[:, 3] - boxes[:, 1]) > threshold)
