"""``panoptic_fpn`` segmenter: detectron2's PanopticFPN (ResNet-FPN, RPN, box/mask heads, semantic FPN head,
panoptic combine) in plain torch, loading detectron2 model-zoo ``.pkl`` and PVO ``.pth`` checkpoints safely, with a
reduced configuration trained here on the synthetic scenarios and shipped in the package (the default).

Modules: ``segmenter`` (the plugin: config, weights, on-demand segmentation, movable flags), ``model``
(PanopticFPN, PanopticOutput), ``config`` (architecture/test settings, presets), ``ops`` (NMS, ROIAlign, box
coding), ``backbone``, ``rpn``, ``roi_heads``, ``semantic``, ``panoptic`` (combine), ``features`` (the batched
pyramid, converted to the core's FeaturePyramid per image), ``categories`` (COCO panoptic / VKITTI2 / synthetic
sets, movable lists), ``checkpoint`` (safe loading), and for training ``targets``, ``losses``, ``data``,
``train`` (``pvslam train segmenter --plugin panoptic_fpn``), ``evaluate`` (PQ per class).
"""
from __future__ import annotations

from pvslam_core.registry import hookimpl


@hookimpl
def register_segmenters(register):  # type: ignore[no-untyped-def]
    from pvslam_core.training import Trainer

    from .segmenter import PanopticFPNSegmenterConfig, make_segmenter
    from .train import TrainConfig, run

    register(
        "panoptic_fpn",
        make_segmenter,
        PanopticFPNSegmenterConfig,
        description="PanopticFPN in plain torch: the reduced model trained on the synthetic scenarios (shipped), "
        "or detectron2's COCO R-50 / PVO's VKITTI2 checkpoints",
        # no auto_ready: the shipped model knows only the synthetic scenes' 13 categories, so it must not replace
        # the labels oracle on a user's own video unasked
        trainer=Trainer(TrainConfig, run, description="the reduced PanopticFPN from scratch on the synthetic "
                        "scenarios' panoptic labels (held-out seeds for validation)"),
    )
