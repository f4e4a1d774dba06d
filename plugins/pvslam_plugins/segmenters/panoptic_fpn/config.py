"""Architecture and test-time settings of PanopticFPN (one pydantic model per part, detectron2's names).

Defaults are detectron2's for ``COCO-PanopticSegmentation/panoptic_fpn_R_50_3x`` (defaults.py + Base-RCNN-FPN.yaml +
Base-Panoptic-FPN.yaml, see reference/checkpoints.md §2).  :func:`preset` returns that configuration (``coco_r50``),
PVO's Virtual KITTI 2 variant (``vkitti2_r50``, §3) and the reduced configuration that trains on this CPU
(``reduced``: same code path, smaller depth and widths).
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pvslam_core.config_base import PluginConfig


class InputConfig(PluginConfig):
    format: Literal["BGR", "RGB"] = Field(
        "BGR", description="channel order the network expects (detectron2 INPUT.FORMAT; pvslam frames are RGB and "
        "are flipped when this is BGR)")
    pixel_mean: tuple[float, float, float] = Field(
        (103.530, 116.280, 123.675), description="per-channel mean in `format` order, on 0..255 pixels")
    pixel_std: tuple[float, float, float] = Field(
        (1.0, 1.0, 1.0), description="per-channel std (MSRA R-50 absorbed the std into conv1, hence 1)")
    min_size_test: int = Field(
        800, ge=0, description="ResizeShortestEdge at test: shorter side in pixels; 0 = no resize")
    max_size_test: int = Field(1333, ge=1, description="cap on the longer side after the resize")
    size_divisibility: int = Field(32, ge=1, description="pad bottom/right to a multiple of this (res5 stride)")


class ResNetConfig(PluginConfig):
    depth: Literal[18, 34, 50, 101] = Field(50, description="18/34 = BasicBlock, 50/101 = BottleneckBlock")
    norm: Literal["FrozenBN", "BN", "GN"] = Field(
        "FrozenBN", description="FrozenBN for pretrained checkpoints; GN (or BN) to train from scratch")
    gn_groups: int = Field(32, ge=1, description="groups when norm = GN")
    stem_out_channels: int = Field(64, ge=1, description="output channels of the stem convolution")
    res2_out_channels: int = Field(256, ge=1, description="output channels of res2; doubled at each later stage")
    width_per_group: int = Field(64, ge=1, description="bottleneck width of res2 (BottleneckBlock only)")
    stride_in_1x1: bool = Field(
        True, description="stride-2 of res3-5 block 0 in conv1 (MSRA models, detectron2 default) rather than in "
        "the 3x3 conv2")


class FPNConfig(PluginConfig):
    out_channels: int = Field(256, ge=1, description="channels of every pyramid level p2..p6")
    norm: Literal["", "GN"] = Field("", description="'' = lateral/output convs with bias, no norm (detectron2)")
    gn_groups: int = Field(32, ge=1, description="groups when norm = GN")


class RPNConfig(PluginConfig):
    anchor_sizes: tuple[float, ...] = Field((32, 64, 128, 256, 512), description="one anchor size per level p2..p6")
    aspect_ratios: tuple[float, ...] = Field((0.5, 1.0, 2.0), description="anchor h/w ratios")
    anchor_offset: float = Field(0.0, description="anchor centres at (x + offset) * stride")
    bbox_reg_weights: tuple[float, float, float, float] = Field(
        (1.0, 1.0, 1.0, 1.0), description="scales of the (dx, dy, dw, dh) box deltas")
    pre_nms_topk_test: int = Field(1000, ge=1, description="proposals kept per level before NMS")
    post_nms_topk_test: int = Field(1000, ge=1, description="proposals kept per image after NMS")
    pre_nms_topk_train: int = Field(2000, ge=1, description="training: proposals kept per level before NMS")
    post_nms_topk_train: int = Field(1000, ge=1, description="training: proposals kept per image after NMS")
    nms_thresh: float = Field(0.7, gt=0.0, le=1.0, description="IoU of the proposals' non-maximum suppression")
    min_size: float = Field(0.0, ge=0.0, description="drop proposals not wider and taller than this")


class BoxHeadConfig(PluginConfig):
    num_classes: int = Field(80, ge=1, description="thing classes (background is an extra last logit)")
    pooler_resolution: int = Field(7, ge=1, description="ROIAlign output side (bins)")
    sampling_ratio: int = Field(0, ge=0, description="ROIAlign samples per bin and axis; 0 = adaptive")
    num_fc: int = Field(2, ge=1, description="fully connected layers of the box head")
    fc_dim: int = Field(1024, ge=1, description="width of those layers")
    bbox_reg_weights: tuple[float, float, float, float] = Field(
        (10.0, 10.0, 5.0, 5.0), description="scales of the (dx, dy, dw, dh) box deltas")
    score_thresh_test: float = Field(0.05, ge=0.0, le=1.0, description="test: boxes scoring below this are dropped")
    nms_thresh_test: float = Field(0.5, gt=0.0, le=1.0, description="test: IoU of the per-class box NMS")
    detections_per_image: int = Field(100, ge=1, description="test: boxes kept per image")
    canonical_box_size: float = Field(224.0, gt=0.0, description="box side mapped to canonical_level")
    canonical_level: int = Field(4, description="FPN level of a canonical_box_size box")


class MaskHeadConfig(PluginConfig):
    pooler_resolution: int = Field(14, ge=1, description="ROIAlign output side (bins)")
    sampling_ratio: int = Field(0, ge=0, description="ROIAlign samples per bin and axis; 0 = adaptive")
    num_conv: int = Field(4, ge=1, description="3x3 convolutions of the mask head")
    conv_dim: int = Field(256, ge=1, description="their channels")
    cls_agnostic: bool = Field(False, description="one mask for all classes instead of one per class")
    mask_threshold: float = Field(0.5, ge=0.0, le=1.0, description="paste threshold on the sigmoid")


class SemSegConfig(PluginConfig):
    num_classes: int = Field(54, ge=2, description="channel 0 = all things, 1.. = stuff classes")
    conv_dims: int = Field(128, ge=1, description="channels of the semantic head's convolutions")
    norm: Literal["GN", ""] = Field("GN", description="their normalisation ('' = none)")
    gn_groups: int = Field(32, ge=1, description="groups when norm = GN")
    common_stride: int = Field(4, description="output stride of the head before the final x4 upsampling")


class CombineConfig(PluginConfig):
    overlap_thresh: float = Field(0.5, ge=0.0, le=1.0, description="drop an instance whose mask is covered more "
                                  "than this by earlier (higher-scoring) instances")
    stuff_area_limit: int = Field(4096, ge=0, description="stuff segments smaller than this (px) are dropped")
    instances_confidence_thresh: float = Field(0.5, ge=0.0, le=1.0, description="instances scoring below this are "
                                               "left out of the panoptic result")


class PanopticFPNConfig(PluginConfig):
    input: InputConfig = Field(InputConfig(), description="input format and test-time resize")
    resnet: ResNetConfig = Field(ResNetConfig(), description="backbone")
    fpn: FPNConfig = Field(FPNConfig(), description="feature pyramid")
    rpn: RPNConfig = Field(RPNConfig(), description="region proposal network")
    box_head: BoxHeadConfig = Field(BoxHeadConfig(), description="box head")
    mask_head: MaskHeadConfig = Field(MaskHeadConfig(), description="mask head")
    sem_seg: SemSegConfig = Field(SemSegConfig(), description="semantic segmentation head")
    combine: CombineConfig = Field(CombineConfig(), description="panoptic combination of instances and stuff")
    categories: str = Field("coco_panoptic", description="category set: coco_panoptic | vkitti2 | a custom name")

    @model_validator(mode="after")
    def _consistent(self) -> "PanopticFPNConfig":
        if len(self.rpn.anchor_sizes) != 5:
            raise ValueError(f"rpn.anchor_sizes: one size per level p2..p6 (5), got {len(self.rpn.anchor_sizes)}")
        if self.resnet.depth in (18, 34) and self.resnet.res2_out_channels != self.resnet.stem_out_channels:
            raise ValueError(
                "resnet: BasicBlock depths (18/34) need res2_out_channels == stem_out_channels "
                f"(got {self.resnet.res2_out_channels} and {self.resnet.stem_out_channels})")
        if self.sem_seg.common_stride != 4:
            raise ValueError("sem_seg.common_stride must be 4 (the stride of p2)")
        if not 2 <= self.box_head.canonical_level <= 5:
            raise ValueError(f"box_head.canonical_level must be in 2..5, got {self.box_head.canonical_level}")
        return self


def _vkitti2() -> PanopticFPNConfig:
    """PVO's panoptic_fpn_R_50_3x_vkitti_*.yaml: 3 thing classes, 12 semantic channels, 375/1242 test resize."""
    return PanopticFPNConfig(
        input=InputConfig(min_size_test=375, max_size_test=1242),
        box_head=BoxHeadConfig(num_classes=3),
        sem_seg=SemSegConfig(num_classes=12),
        categories="vkitti2",
    )


def reduced(num_thing_classes: int = 3, num_sem_classes: int = 11, categories: str = "synthetic") -> PanopticFPNConfig:
    """A small PanopticFPN that trains from scratch on this CPU (same modules, fewer/narrower layers).

    R-18-style BasicBlock backbone at half width (32-64-128-256 channels) with GroupNorm (FrozenBN cannot learn
    statistics from scratch), FPN and heads at 64 channels, fewer proposals/detections; native resolution
    (no test resize) and RGB input normalised to roughly unit scale."""
    return PanopticFPNConfig(
        input=InputConfig(format="RGB", pixel_mean=(123.675, 116.28, 103.53), pixel_std=(58.395, 57.12, 57.375),
                          min_size_test=0),
        resnet=ResNetConfig(depth=18, norm="GN", gn_groups=8, stem_out_channels=32, res2_out_channels=32),
        fpn=FPNConfig(out_channels=64),
        rpn=RPNConfig(pre_nms_topk_test=300, post_nms_topk_test=100, pre_nms_topk_train=300,
                      post_nms_topk_train=150, anchor_sizes=(16, 32, 64, 128, 256)),
        # fixed 2x2 ROIAlign samples: one sampling grid per image and level (adaptive sampling makes one per box
        # size), which keeps the training step cheap; the test uses the same setting
        box_head=BoxHeadConfig(num_classes=num_thing_classes, fc_dim=256, detections_per_image=50, sampling_ratio=2),
        mask_head=MaskHeadConfig(num_conv=2, conv_dim=64, sampling_ratio=2),
        sem_seg=SemSegConfig(num_classes=num_sem_classes, conv_dims=64, gn_groups=16),
        combine=CombineConfig(stuff_area_limit=320),  # 4096 px of an ~800x1200 COCO input, as a 320x240 fraction
        categories=categories,
    )


PRESETS = {"coco_r50": PanopticFPNConfig, "vkitti2_r50": _vkitti2, "reduced": reduced}
# the preset names as a config field type (the segmenter and the fusion VPS head, which decodes with its heads)
PresetName = Literal["reduced", "coco_r50", "vkitti2_r50"]


def preset(name: str) -> PanopticFPNConfig:
    """``coco_r50`` (detectron2 model zoo), ``vkitti2_r50`` (PVO's checkpoint) or ``reduced`` (trainable here)."""
    if name not in PRESETS:
        raise ValueError(f"unknown PanopticFPN preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name]()

