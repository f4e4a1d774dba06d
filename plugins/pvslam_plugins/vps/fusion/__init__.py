"""``fusion`` VPS head: PVO's VO-enhanced video panoptic segmentation.

The previous frame's FPN features are forward-warped into the current frame per level with the VO's flow (depth
z-ordering, rigid flow from depth + poses for static regions), fused with the current features by PVO's
``fusion_conv1`` (3x3, 2C -> C; PVO's converted layer loads strictly), decoded by the ``panoptic_fpn`` segmenter's
own heads, and matched to the previous ids with the instance matching shared with ``warp_iou``
(:mod:`pvslam_plugins.vps.matching`), plus a short track memory that gives an occluded car its id back.
Only the fusion layer trains: ``pvslam train vps --plugin fusion``.

Modules: ``config``, ``feature_warp`` (per-level forward warping), ``layer`` (fusion_conv1, loading), ``head``
(the VPS head), ``train`` (trainer), ``data`` (consecutive-frame pairs from the generator).

Registered as VPS plugin ``fusion``.
"""
from __future__ import annotations

from pvslam_core.registry import hookimpl


@hookimpl
def register_vps_heads(register):  # type: ignore[no-untyped-def]
    from pvslam_core.training import Trainer

    from .config import FusionConfig
    from .head import make_vps_head
    from .train import TrainConfig, run

    register(
        "fusion",
        make_vps_head,
        FusionConfig,
        description="PVO feature fusion: warp the previous FPN features by VO flow/depth/pose, fuse_conv1, decode "
        "with the panoptic_fpn heads, shared overlap matching + track memory",
        trainer=Trainer(TrainConfig, run, description="only fusion_conv1, from the shipped panoptic_fpn "
                        "checkpoint, on consecutive frames of the generator's moving-vehicle scenarios"),
    )
