"""PanopticFPN's training losses (detectron2's PanopticFPN in training mode), on the same modules as inference.

    loss = sem_weight * CE(semantic logits, semantic labels; void ignored)                (SemSegFPNHead)
         + BCE(objectness of sampled anchors) + L1(deltas of positive anchors)            (RPN)
         + CE(class of sampled proposals)     + L1(class-specific deltas of positives)    (box head)
         + BCE(28x28 mask of the ground-truth class on positive proposals)                 (mask head)

detectron2's normalisations: both RPN terms are divided by ``rpn_batch * images``, the box L1 by the number of
sampled proposals, the CE/BCE terms are means.  Proposals for the ROI heads come from the RPN's own (detached)
outputs plus the ground-truth boxes, sampled at ``roi_batch`` per image with ``roi_positive_fraction`` positives.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from .model import ROI_LEVELS, RPN_LEVELS, PanopticFPN
from .targets import encode_deltas, mask_targets, match, subsample

__all__ = ["InstanceTargets", "LossWeights", "panoptic_fpn_losses", "pyramid_losses", "IGNORE"]

#: semantic label of pixels that do not count (void, padding)
IGNORE = 255


@dataclass
class InstanceTargets:
    """Thing instances of one image, in network-input pixels."""

    boxes: torch.Tensor  # float [G, 4] tight boxes x0, y0, x1, y1
    classes: torch.Tensor  # int64 [G] contiguous thing class 0..K-1
    masks: torch.Tensor  # bool [G, H, W] (H, W = the image, unpadded)


@dataclass
class LossWeights:
    sem_seg: float = 0.5  # detectron2 Panoptic-FPN SEM_SEG_HEAD.LOSS_WEIGHT
    instances: float = 1.0  # PANOPTIC_FPN.INSTANCE_LOSS_WEIGHT
    rpn_batch: int = 256  # RPN.BATCH_SIZE_PER_IMAGE
    rpn_positive_fraction: float = 0.5
    rpn_iou: tuple[float, float] = (0.3, 0.7)
    roi_batch: int = 64  # ROI_HEADS.BATCH_SIZE_PER_IMAGE (512 in detectron2: fewer objects and a CPU budget here)
    roi_positive_fraction: float = 0.25
    roi_iou: float = 0.5


def _rpn_losses(model: PanopticFPN, feats: list[torch.Tensor], targets: list[InstanceTargets],
                image_sizes: list[tuple[int, int]], w: LossWeights, gen: Optional[torch.Generator]):
    rpn = model.proposal_generator
    logits, deltas = rpn.head_outputs(feats)  # per level [B, A_l], [B, A_l, 4]
    anchors = rpn.anchors(feats)
    all_anchors = torch.cat(anchors)  # [A, 4]
    all_logits, all_deltas = torch.cat(logits, dim=1), torch.cat(deltas, dim=1)
    cls_terms, loc_terms = [], []
    for b, t in enumerate(targets):
        matched, labels = match(t.boxes, all_anchors, *w.rpn_iou, allow_low_quality=True)
        pos, neg = subsample(labels, w.rpn_batch, w.rpn_positive_fraction, gen)
        idx = torch.cat([pos, neg])
        target = torch.cat([torch.ones_like(pos), torch.zeros_like(neg)]).float()
        cls_terms.append(F.binary_cross_entropy_with_logits(all_logits[b, idx], target, reduction="sum"))
        if pos.numel():
            goal = encode_deltas(all_anchors[pos], t.boxes[matched[pos]], model.cfg.rpn.bbox_reg_weights)
            loc_terms.append(F.l1_loss(all_deltas[b, pos], goal, reduction="sum"))
    norm = float(w.rpn_batch * len(targets))
    loss_cls = torch.stack(cls_terms).sum() / norm
    loss_loc = (torch.stack(loc_terms).sum() if loc_terms else all_deltas.sum() * 0.0) / norm
    with torch.no_grad():
        proposals = rpn.select(anchors, [x.detach() for x in logits], [x.detach() for x in deltas], image_sizes,
                               training=True)
    return {"loss_rpn_cls": loss_cls, "loss_rpn_loc": loss_loc}, proposals


def _roi_losses(model: PanopticFPN, feats: list[torch.Tensor], proposals, targets: list[InstanceTargets],
                w: LossWeights, gen: Optional[torch.Generator]):
    heads = model.roi_heads
    k = heads.num_classes
    boxes, classes, matched_all, fg_counts = [], [], [], []
    for p, t in zip(proposals, targets):
        cand = torch.cat([p.boxes, t.boxes.to(p.boxes.dtype)])  # append the ground truth (detectron2 default)
        matched, labels = match(t.boxes, cand, w.roi_iou, w.roi_iou)
        pos, neg = subsample(labels, w.roi_batch, w.roi_positive_fraction, gen)
        sel = torch.cat([pos, neg])
        cls = torch.full((sel.numel(),), k, dtype=torch.int64, device=cand.device)
        if t.boxes.shape[0]:
            cls[: pos.numel()] = t.classes[matched[pos]]
        boxes.append(cand[sel])
        classes.append(cls)
        matched_all.append(matched[sel])
        fg_counts.append(int(pos.numel()))
    logits, deltas = heads.box_outputs(feats, boxes)
    gt_cls = torch.cat(classes)
    loss_cls = F.cross_entropy(logits, gt_cls)
    fg = torch.nonzero(gt_cls < k).squeeze(1)
    if fg.numel():
        src = torch.cat(boxes)[fg]
        tgt = torch.cat([t.boxes[m[:n]] for t, m, n in zip(targets, matched_all, fg_counts) if n])
        goal = encode_deltas(src, tgt, heads.box_cfg.bbox_reg_weights)
        pred = deltas.view(deltas.shape[0], k, 4)[fg, gt_cls[fg]]
        loss_loc = F.l1_loss(pred, goal, reduction="sum") / max(gt_cls.numel(), 1)
    else:
        loss_loc = deltas.sum() * 0.0
    # masks: positives only, each against its ground-truth instance cropped to the proposal
    fg_boxes = [b[:n] for b, n in zip(boxes, fg_counts)]
    if sum(fg_counts):
        mlogits = heads.mask_logits(feats, fg_boxes)  # [R, K or 1, M, M]
        size = int(mlogits.shape[-1])
        mtargets, mclasses = [], []
        for t, b, m, n in zip(targets, fg_boxes, matched_all, fg_counts):
            if n:
                mtargets.append(mask_targets(t.masks, b, m[:n], size))
                mclasses.append(t.classes[m[:n]])
        mcls = torch.cat(mclasses)
        pick = mlogits[torch.arange(mlogits.shape[0]), mcls if mlogits.shape[1] > 1 else torch.zeros_like(mcls)]
        loss_mask = F.binary_cross_entropy_with_logits(pick, torch.cat(mtargets))
    else:
        loss_mask = sum(p.sum() for p in heads.mask_head.parameters()) * 0.0
    return {"loss_cls": loss_cls, "loss_box_reg": loss_loc, "loss_mask": loss_mask}


def panoptic_fpn_losses(model: PanopticFPN, images: torch.Tensor, image_sizes: list[tuple[int, int]],
                        semantic: torch.Tensor, targets: list[InstanceTargets], weights: LossWeights = LossWeights(),
                        generator: Optional[torch.Generator] = None) -> dict[str, torch.Tensor]:
    """All PanopticFPN losses on a normalised, padded batch ``images [B, 3, Hp, Wp]``.

    ``semantic`` int64 ``[B, Hp, Wp]``: semantic channel per pixel (0 = things), :data:`IGNORE` on void/padding;
    ``targets``: one :class:`InstanceTargets` per image.  Returns the weighted terms (their sum is the loss)."""
    pyr = model.extract_normalised(images, image_sizes)
    return pyramid_losses(model, pyr, semantic, targets, weights, generator)


def pyramid_losses(model: PanopticFPN, pyr, semantic: torch.Tensor, targets: list[InstanceTargets],
                   weights: LossWeights = LossWeights(), generator: Optional[torch.Generator] = None
                   ) -> dict[str, torch.Tensor]:
    """The losses of :func:`panoptic_fpn_losses` on a given :class:`~.features.PyramidBatch` (e.g. fused
    features of a VPS head: gradients flow into whatever produced ``pyr``)."""
    image_sizes = pyr.image_sizes
    sem_logits = model.semantic_logits(pyr)
    out = {"loss_sem_seg": weights.sem_seg * F.cross_entropy(sem_logits, semantic, ignore_index=IGNORE)}
    rpn_losses, proposals = _rpn_losses(model, pyr.select(RPN_LEVELS), targets, image_sizes, weights, generator)
    roi_losses = _roi_losses(model, pyr.select(ROI_LEVELS), proposals, targets, weights, generator)
    for k, v in {**rpn_losses, **roi_losses}.items():
        out[k] = weights.instances * v
    return out
