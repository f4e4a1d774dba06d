"""PanopticFPN (Kirillov et al. 2019, detectron2's implementation) assembled from this package's parts.

    frames (uint8 RGB [3, H, W]) --preprocess--> normalised, resized, padded batch
        --backbone (ResNet + FPN)--> PyramidBatch p2..p6
        --decode--> semantic head (p2-p5), RPN (p2-p6), box + mask heads (p2-p5), panoptic combine

``decode`` takes any :class:`~.features.PyramidBatch` with the geometry of ``extract``'s, so a VPS fusion head can run
fused features through the same heads.  Top-level module names equal detectron2's (``backbone``,
``proposal_generator``, ``roi_heads``, ``sem_seg_head``), so a converted state_dict loads by name.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from pvslam_core.types import PanopticSegmentation, Segment

from .backbone import FPN, ResNet
from .categories import BUILTIN_SETS, CategorySet, category_set
from .config import PanopticFPNConfig
from .features import PyramidBatch
from .panoptic import argmax_channels, combine, detector_postprocess, semantic_postprocess
from .roi_heads import Detections, ROIHeads
from .rpn import RPN, Proposals
from .semantic import SemSegFPNHead

__all__ = ["PanopticFPN", "PanopticOutput", "resized_shape"]

ROI_LEVELS = ("p2", "p3", "p4", "p5")
RPN_LEVELS = ("p2", "p3", "p4", "p5", "p6")


def resized_shape(h: int, w: int, min_size: int, max_size: int) -> tuple[int, int]:
    """detectron2 ResizeShortestEdge.get_output_shape: shorter side to ``min_size``, longer capped at
    ``max_size``, rounded with ``int(x + 0.5)``; ``min_size == 0`` keeps the size."""
    if min_size <= 0:
        return h, w
    scale = min_size / min(h, w)
    newh, neww = (float(min_size), scale * w) if h < w else (scale * h, float(min_size))
    if max(newh, neww) > max_size:
        scale = max_size / max(newh, neww)
        newh, neww = newh * scale, neww * scale
    return int(newh + 0.5), int(neww + 0.5)


@dataclass
class PanopticOutput:
    """Result for one frame, at the frame's resolution."""

    ids: torch.Tensor  # int64 [H, W], 0 = void, segment ids 1, 2, ...
    segments: list[Segment]  # category_id = dataset category id of the model's CategorySet
    detections: Detections  # boxes [N, 4] in frame pixels, scores, contiguous classes, masks bool [N, H, W]
    semantic: torch.Tensor  # int64 [H, W] argmax semantic channel (0 = things)
    features: PyramidBatch  # this frame's pyramid (batch of 1)

    def to_panoptic(self, with_features: bool = True) -> PanopticSegmentation:
        """The core's segmentation; ``features`` the core's per-image FeaturePyramid p2..p6 (or None)."""
        return PanopticSegmentation(self.ids, list(self.segments),
                                    self.features.to_core(0) if with_features else None)


class PanopticFPN(nn.Module):
    def __init__(self, cfg: Optional[PanopticFPNConfig] = None, categories: Optional[CategorySet] = None) -> None:
        super().__init__()
        cfg = cfg or PanopticFPNConfig()
        self.cfg = cfg
        if categories is None:
            if cfg.categories not in BUILTIN_SETS:
                raise ValueError(f"category set {cfg.categories!r} is not built in ({', '.join(BUILTIN_SETS)}); "
                                 "pass a CategorySet")
            categories = category_set(cfg.categories)
        if categories.num_thing_classes != cfg.box_head.num_classes or \
                categories.num_sem_classes != cfg.sem_seg.num_classes:
            raise ValueError(
                f"category set {categories.name!r} has {categories.num_thing_classes} thing classes and "
                f"{categories.num_sem_classes} semantic channels (1 + stuff); the config has box_head.num_classes="
                f"{cfg.box_head.num_classes} and sem_seg.num_classes={cfg.sem_seg.num_classes}")
        self.categories = categories
        self.backbone = FPN(ResNet(cfg.resnet), cfg.fpn)
        strides = self.backbone.strides
        c = cfg.fpn.out_channels
        self.proposal_generator = RPN(cfg.rpn, c, [strides[k] for k in RPN_LEVELS])
        self.roi_heads = ROIHeads(cfg.box_head, cfg.mask_head, c, [strides[k] for k in ROI_LEVELS])
        self.sem_seg_head = SemSegFPNHead(cfg.sem_seg, c, {k: strides[k] for k in ROI_LEVELS})
        # not persistent: detectron2's model-zoo files do not carry them (the loader accepts them if present)
        self.register_buffer("pixel_mean", torch.tensor(cfg.input.pixel_mean).view(3, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(cfg.input.pixel_std).view(3, 1, 1), persistent=False)
        self.register_buffer("_thing_ids", categories.thing_ids(), persistent=False)
        self.register_buffer("_sem_ids", categories.semantic_ids(), persistent=False)
        self.eval()

    @property
    def device(self) -> torch.device:
        return self.pixel_mean.device

    # ------------------------------------------------------------------------------------------------- input
    def preprocess(self, images: Sequence[torch.Tensor] | torch.Tensor
                   ) -> tuple[torch.Tensor, list[tuple[int, int]], list[tuple[int, int]]]:
        """RGB frames ``[3, H, W]`` (uint8 0..255, or float on the same scale) -> normalised batch
        ``[B, 3, Hp, Wp]`` (resized per the test policy, zero-padded after normalisation to a multiple of
        ``size_divisibility``), network input sizes and frame sizes, each ``(h, w)`` per image."""
        if isinstance(images, torch.Tensor):
            images = list(images) if images.dim() == 4 else [images]
        icfg = self.cfg.input
        tensors, sizes, out_sizes = [], [], []
        for img in images:
            if img.dim() != 3 or img.shape[0] != 3:
                raise ValueError(f"expected an RGB image [3, H, W], got shape {tuple(img.shape)}")
            h, w = int(img.shape[1]), int(img.shape[2])
            x = img.to(self.device, torch.float32)
            nh, nw = resized_shape(h, w, icfg.min_size_test, icfg.max_size_test)
            if (nh, nw) != (h, w):
                # detectron2 resizes the uint8 image with PIL BILINEAR; antialiased bilinear + rounding matches
                # it up to PIL's fixed-point rounding (+-1 grey level)
                x = F.interpolate(x[None], size=(nh, nw), mode="bilinear", align_corners=False,
                                  antialias=True)[0]
                if img.dtype == torch.uint8:
                    x = x.round().clamp(0, 255)
            if icfg.format == "BGR":
                x = x.flip(0)
            tensors.append((x - self.pixel_mean) / self.pixel_std)
            sizes.append((nh, nw))
            out_sizes.append((h, w))
        d = icfg.size_divisibility
        hp = -(-max(s[0] for s in sizes) // d) * d
        wp = -(-max(s[1] for s in sizes) // d) * d
        batch = tensors[0].new_zeros((len(tensors), 3, hp, wp))
        for i, t in enumerate(tensors):
            batch[i, :, : t.shape[1], : t.shape[2]] = t
        return batch, sizes, out_sizes

    # ------------------------------------------------------------------------------------------------ stages
    def extract(self, images: Sequence[torch.Tensor] | torch.Tensor) -> PyramidBatch:
        """Backbone + FPN on RGB frames -> :class:`PyramidBatch` p2..p6 (strides 4..64)."""
        batch, sizes, out_sizes = self.preprocess(images)
        return self.extract_normalised(batch, sizes, out_sizes)

    def extract_normalised(self, batch: torch.Tensor, image_sizes: list[tuple[int, int]],
                           output_sizes: Optional[list[tuple[int, int]]] = None) -> PyramidBatch:
        levels = self.backbone(batch)
        return PyramidBatch(levels, dict(self.backbone.strides), list(image_sizes),
                              list(output_sizes or image_sizes))

    def pyramid_for(self, levels: Mapping[str, torch.Tensor], frame_size: tuple[int, int]) -> PyramidBatch:
        """A one-image :class:`PyramidBatch` of given maps (``[C, h, w]`` or ``[1, C, h, w]`` per level, e.g. a
        frame's features from ``PanopticSegmentation.features`` or fused ones) with the geometry :meth:`extract`
        gives a frame of ``frame_size`` ``(H, W)``, ready for :meth:`decode`."""
        H, W = int(frame_size[0]), int(frame_size[1])
        missing = [k for k in self.backbone.strides if k not in levels]
        if missing:
            raise KeyError(f"pyramid_for: level(s) {missing} missing; got {list(levels)}")
        nh, nw = resized_shape(H, W, self.cfg.input.min_size_test, self.cfg.input.max_size_test)
        maps = {k: (levels[k] if levels[k].dim() == 4 else levels[k][None]) for k in self.backbone.strides}
        return PyramidBatch(maps, dict(self.backbone.strides), [(nh, nw)], [(H, W)])

    def semantic_logits(self, pyramid: PyramidBatch) -> torch.Tensor:
        """``[B, S, Hp, Wp]`` semantic logits at the padded input resolution."""
        return self.sem_seg_head(pyramid.select(ROI_LEVELS))

    def propose(self, pyramid: PyramidBatch) -> list[Proposals]:
        return self.proposal_generator(pyramid.select(RPN_LEVELS), pyramid.image_sizes)

    def detect(self, pyramid: PyramidBatch, proposals: list[Proposals]) -> list[Detections]:
        """Final boxes, scores, classes and 28x28 mask probabilities, in network-input pixels."""
        return self.roi_heads.detect(pyramid.select(ROI_LEVELS), [p.boxes for p in proposals],
                                     pyramid.image_sizes)

    @torch.no_grad()
    def decode(self, pyramid: PyramidBatch) -> list[PanopticOutput]:
        """All heads and the panoptic combine on a pyramid (own or fused) -> one :class:`PanopticOutput` per image."""
        sem = self.semantic_logits(pyramid)
        dets = self.detect(pyramid, self.propose(pyramid))
        comb = self.cfg.combine
        outs = []
        for i, (d, size, out_size) in enumerate(zip(dets, pyramid.image_sizes, pyramid.output_sizes)):
            logits = semantic_postprocess(sem[i], size, out_size)
            labels, label_probs = argmax_channels(logits)
            d = detector_postprocess(d, size, out_size, self.cfg.mask_head.mask_threshold)
            seg = combine(d.masks, d.scores, d.classes, labels, comb.overlap_thresh, comb.stuff_area_limit,
                          comb.instances_confidence_thresh, label_probs=label_probs, boxes=d.boxes)
            segments = [
                Segment(sid, int(self._thing_ids[lab] if thing else self._sem_ids[lab]), thing, score)
                for sid, (thing, lab, score) in enumerate(zip(seg.isthing, seg.labels, seg.scores), start=1)
            ]
            outs.append(PanopticOutput(seg.ids, segments, d, labels, pyramid.image(i)))
        return outs

    @torch.no_grad()
    def forward(self, images: Sequence[torch.Tensor] | torch.Tensor) -> list[PanopticOutput]:
        return self.decode(self.extract(images))

    def segment(self, image: torch.Tensor) -> PanopticOutput:
        """One RGB frame ``[3, H, W]`` -> its :class:`PanopticOutput`."""
        return self.forward([image])[0]
