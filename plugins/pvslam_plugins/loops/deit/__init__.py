"""``deit`` loop detector: DeiT-base / DeiT-base-distilled global descriptors (paper eq. 8-13).

Modules:

* :mod:`.vit`: timm-0.3.3 ``VisionTransformer`` / DeiT ``DistilledVisionTransformer`` with upstream parameter
  names, any input size via position-embedding resampling, presets ``deit_base_patch16_224`` (152 keys) and
  ``deit_base_distilled_patch16_224`` (155 keys);
* :mod:`.checkpoint`: official ``.pth`` and project-format loading (strict, with a key/shape report), saving;
* :mod:`.preprocess`: DeiT eval transform / full-frame resize, ImageNet normalisation;
* :mod:`.descriptor`: batched raw descriptors (layer-normed class token and variants), model construction;
* :mod:`.pca`: PCA / whitening, fixed or fitted online;
* :mod:`.retrieval`: id-keyed descriptor index, cosine retrieval with threshold / temporal exclusion;
* :mod:`.detector`: the :class:`~pvslam_core.interfaces.LoopDetector` (batched descriptors, optional geometric
  verification through the shared :mod:`pvslam_plugins.loops.verification`);
* :mod:`.train`: ``pvslam train loop --plugin deit``: a small DeiT trained contrastively on the built-in generator;
* :mod:`.config`: the flat detector config.

Registered as loop plugin ``deit`` (entry point ``deit``), with a trainer.
"""
from __future__ import annotations

from pvslam_core.registry import hookimpl


@hookimpl
def register_loop_detectors(register):  # type: ignore[no-untyped-def]
    from pvslam_core.training import Trainer

    from .config import DeitLoopConfig
    from .detector import make_loop_detector
    from .train import DeitTrainConfig, run_training

    register(
        "deit",
        make_loop_detector,
        DeitLoopConfig,
        description="DeiT-base / DeiT-base-distilled global descriptors (eq. 12), cosine retrieval, optional "
        "ORB + essential-matrix verification (shared with classical)",
        trainer=Trainer(DeitTrainConfig, run_training,
                        description="small DeiT trained contrastively on the synthetic generator's revisits"),
    )
