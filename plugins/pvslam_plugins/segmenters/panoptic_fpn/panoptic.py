"""Post-processing to the frame's resolution and the panoptic combine (detectron2 postprocessing.py and
meta_arch/panoptic_fpn.py ``combine_semantic_and_instance_outputs``; reference/checkpoints.md §2.8)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .ops import clip_boxes, nonempty
from .roi_heads import Detections, paste_masks

__all__ = ["semantic_postprocess", "detector_postprocess", "combine", "argmax_channels", "PanopticSegments"]


def semantic_postprocess(logits: torch.Tensor, image_size: tuple[int, int],
                         output_size: tuple[int, int]) -> torch.Tensor:
    """``[S, Hp, Wp]`` logits on the padded input -> ``[S, H, W]``: crop the padding, bilinear resize."""
    h, w = image_size
    x = logits[None, :, :h, :w]
    if (h, w) != tuple(output_size):
        x = F.interpolate(x, size=tuple(output_size), mode="bilinear", align_corners=False)
    return x[0]


def detector_postprocess(dets: Detections, image_size: tuple[int, int], output_size: tuple[int, int],
                         mask_threshold: float = 0.5) -> Detections:
    """Scale boxes from the network input to the frame, clip, drop empty boxes, paste masks (bool ``[N, H, W]``)."""
    sy = output_size[0] / image_size[0]
    sx = output_size[1] / image_size[1]
    boxes = dets.boxes * torch.tensor([sx, sy, sx, sy], dtype=dets.boxes.dtype, device=dets.boxes.device)
    boxes = clip_boxes(boxes, output_size)
    out = Detections(boxes, dets.scores, dets.classes, dets.mask_probs, None).take(nonempty(boxes))
    if out.mask_probs is not None:
        out.masks = paste_masks(out.mask_probs, out.boxes, output_size, mask_threshold)
    return out


@dataclass
class PanopticSegments:
    """Combine result in network terms: ``ids`` int64 ``[H, W]`` (0 = void, segments 1, 2, ...), and per segment
    ``isthing``, ``label`` (contiguous thing class, or semantic channel for stuff), ``score``, ``instance``
    (index into the detections, -1 for stuff)."""

    ids: torch.Tensor
    isthing: list[bool]
    labels: list[int]
    scores: list[float]
    instances: list[int]
    areas: list[int]


def _box_region(box: torch.Tensor, h: int, w: int) -> tuple[slice, slice]:
    """Rows/cols of a pasted mask's support: its box grown by one pixel (paste_masks never writes outside it)."""
    x0, y0, x1, y1 = box.tolist()
    return (slice(max(int(y0) - 1, 0), min(int(-(-y1 // 1)) + 1, h)),
            slice(max(int(x0) - 1, 0), min(int(-(-x1 // 1)) + 1, w)))


def combine(masks: torch.Tensor, scores: torch.Tensor, classes: torch.Tensor, semantic: torch.Tensor,
            overlap_thresh: float = 0.5, stuff_area_limit: int = 4096,
            instances_confidence_thresh: float = 0.5, label_probs: torch.Tensor | None = None,
            boxes: torch.Tensor | None = None) -> PanopticSegments:
    """detectron2's heuristic panoptic merge.

    Instances by decreasing score (stop below ``instances_confidence_thresh``): skip empty masks and masks whose
    overlap with already-assigned pixels exceeds ``overlap_thresh`` of their area; otherwise claim their
    unassigned pixels as a new segment.  Then every semantic label except 0 ("things") whose unassigned pixels
    cover at least ``stuff_area_limit`` pixels (and at least one) becomes one stuff segment, in increasing label
    order.

    ``masks`` bool ``[N, H, W]``, ``scores`` ``[N]``, ``classes`` ``[N]``, ``semantic`` int64 ``[H, W]`` argmax
    labels.  ``label_probs`` (optional ``[H, W]``, the probability of each pixel's argmax label) gives stuff
    segments a score (their mean), otherwise 1.0.  ``boxes`` (optional ``[N, 4]``) promises that each mask is
    empty outside its box grown by one pixel, as :func:`~.roi_heads.paste_masks` guarantees; the per-instance work
    is then done on that window only.
    """
    h, w = semantic.shape
    ids = torch.zeros((h, w), dtype=torch.int64, device=semantic.device)
    seg = PanopticSegments(ids, [], [], [], [], [])
    # the instance loop is sequential by definition (each claims pixels the next cannot); at most
    # detections_per_image iterations of window-sized tensor ops
    order = torch.argsort(-scores, stable=True).tolist()
    score_list = scores.tolist()
    for i in order:
        if score_list[i] < instances_confidence_thresh:
            break
        win = _box_region(boxes[i], h, w) if boxes is not None else (slice(None), slice(None))
        mask, ids_win = masks[i][win], ids[win]
        area = int(mask.sum())
        if area == 0:
            continue
        free = ids_win == 0
        inter = area - int((mask & free).sum())
        if inter / area > overlap_thresh:
            continue
        if inter > 0:
            mask = mask & free
        ids_win[mask] = len(seg.labels) + 1
        seg.isthing.append(True)
        seg.labels.append(int(classes[i]))
        seg.scores.append(float(score_list[i]))
        seg.instances.append(i)
        seg.areas.append(area - inter)
    # stuff in whole-image passes: free pixels' labels (taken pixels -> an extra "none" bin), their areas, and
    # a lookup table label -> new segment id
    free = ids == 0
    num_labels = int(semantic.max()) + 1 if semantic.numel() else 1
    free_labels = torch.where(free, semantic, torch.full_like(semantic, num_labels))
    area = torch.bincount(free_labels.flatten(), minlength=num_labels + 1)[:num_labels]
    labels = [lab for lab in torch.nonzero(area >= max(stuff_area_limit, 1)).squeeze(1).tolist() if lab != 0]
    if labels:
        first = len(seg.labels) + 1
        lut = torch.zeros(num_labels + 1, dtype=torch.int64, device=ids.device)
        lut[torch.tensor(labels, device=ids.device)] = torch.arange(first, first + len(labels), device=ids.device)
        ids.copy_(torch.where(free, lut[free_labels], ids))
        if label_probs is not None:
            sums = torch.bincount(ids.flatten(), weights=label_probs.flatten().double(), minlength=first + len(labels))
        for k, lab in enumerate(labels):
            seg.isthing.append(False)
            seg.labels.append(int(lab))
            seg.scores.append(float(sums[first + k] / area[lab]) if label_probs is not None else 1.0)
            seg.instances.append(-1)
            seg.areas.append(int(area[lab]))
    return seg


def argmax_channels(logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``[S, H, W]`` -> (argmax label int64 ``[H, W]``, softmax probability of that label ``[H, W]``).

    One pass per channel over contiguous planes: torch's reduction over the leading (strided) dimension is
    several times slower on the CPU.  Ties go to the lowest channel, as ``argmax``."""
    best = logits[0].clone()
    label = torch.zeros(best.shape, dtype=torch.int64, device=logits.device)
    for c in range(1, logits.shape[0]):
        better = logits[c] > best
        best = torch.where(better, logits[c], best)
        label.masked_fill_(better, c)
    denom = torch.zeros_like(best)
    for c in range(logits.shape[0]):
        denom += torch.exp(logits[c] - best)
    return label, 1.0 / denom
