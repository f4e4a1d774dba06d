"""DeiT global descriptor of a keyframe: ``y = L2(PCA(LN(T_K^0)))`` (paper eq. 12, cosine similarity eq. 8).

:class:`DeitDescriptor` turns RGB frames into *raw* descriptors, the layer-normed token(s) of the final ``norm``
(``features``), batched (``batch_size`` keyframes per forward pass) and without gradients.  The PCA/whitening
and the L2 normalisation are model-independent and live with the descriptors (:mod:`.pca`,
:class:`~.retrieval.KeyframeIndex`), because an online PCA re-projects old descriptors when it is refit;
``describe`` applies them for one-off use.

Token choice (``token``): eq. 12 reads the final layer-normed token 0 and eq. 9 builds the sequence from
``x_class`` and the patches only, so the paper's descriptor is the **class token** (``cls``), also for the
distilled model it uses.  ``dist``, ``mean`` ((cls + dist) / 2, timm's pre-logits of distilled DeiT, whose
classifier averages the two heads) and ``concat`` ([cls, dist], 2D) are offered for the ablation.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import torch

from .checkpoint import CheckpointError, LoadedCheckpoint, load_checkpoint
from .config import BUILTIN, DeitDescriptorConfig, DeitModelConfig
from .pca import OnlinePCA, PCAWhitening
from .preprocess import Images, preprocess
from .retrieval import Projector, l2_normalize
from .vit import VisionTransformer, deit_base_distilled_patch16_224, deit_base_patch16_224

LOG = logging.getLogger("pvslam")

TOKENS = ("cls", "dist", "mean", "concat")
#: center_crop: DeiT's evaluation crop ratio (224 / 256)
CROP_PCT = 0.875
#: online PCA whitening regulariser: scale 1 / sqrt(eig + WHITEN_SHRINKAGE * mean(eig)), so small components stay small
WHITEN_SHRINKAGE = 0.1
#: online PCA: refit when the number of keyframes seen grew by this factor (a geometric schedule)
PCA_REFIT_GROWTH = 1.25

_VARIANT_NAMES = {"base": "plain", "distilled": "distilled"}  # config variant -> ViTConfig.variant

#: the checkpoints shipped with the package (trained by :mod:`.train`), one per variant
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


#: sha256 of the shipped checkpoints (weights/README.md): a file that differs is corrupt (truncated copy, a Git LFS
#: pointer instead of the data) or was replaced; loading it anyway could silently give wrong loops
SHIPPED_SHA256 = {
    "base": "0c0e1d70e001fb6fe54d0a2c72ae474a4c59c67daf036ed103d45a66579f7d7b",
    "distilled": "50f4fb0f2a6eb5555ef55a6e6d5764d5829369952c797e8ad1de5b7d6f61a921",
}


def builtin_weights(variant: str) -> Optional[Path]:
    """The shipped checkpoint of a variant (``base`` | ``distilled``), or None when none is shipped."""
    p = WEIGHTS_DIR / f"deit_synth_{variant}.pt"
    return p if p.is_file() else None


def check_builtin_weights(variant: str) -> Path:
    """The shipped checkpoint of a variant, checked: :class:`FileNotFoundError` when it is missing,
    :class:`CheckpointError` when its sha256 is not the shipped one (both name the file and what to do)."""
    from pvslam_core.weights import check_shipped

    fix = ("reinstall pvslam (the file is package data of pvslam_plugins.loops.deit), or set loop.weights to "
           "another checkpoint, or loop.plugin = 'classical'")
    return check_shipped(WEIGHTS_DIR / f"deit_synth_{variant}.pt", SHIPPED_SHA256[variant],
                         f"deit loop detector (loop.weights = 'builtin', {variant})", fix, error=CheckpointError)


def resolve_model_weights(config: DeitModelConfig) -> Optional[Path]:
    """The file ``config.weights`` names: None (random init) for None / 'none'; the checked shipped checkpoint
    for 'builtin' (missing or corrupt: an error, never a silent random model); a catalogue name or a path through
    :func:`pvslam_core.weights.resolve_weights`."""
    if config.weights is None or config.weights == "none":
        return None
    if config.weights == BUILTIN:
        return check_builtin_weights(config.variant)
    from pvslam_core.weights import resolve_weights

    return resolve_weights(config.weights)


def select_tokens(tokens: torch.Tensor, token: str = "cls", num_prefix_tokens: int = 1) -> torch.Tensor:
    """Raw descriptor from final-norm tokens ``[B, N, D]`` -> ``[B, D]`` (``[B, 2D]`` for ``concat``).

    Differentiable (training can use it on ``model.forward_tokens`` output).
    """
    if token == "cls":
        return tokens[:, 0]
    if token not in TOKENS:
        raise ValueError(f"unknown token choice {token!r}; choose one of {TOKENS}")
    if num_prefix_tokens < 2:
        raise ValueError(f"token={token!r} needs the distilled model (a distillation token); this one has none")
    cls, dist = tokens[:, 0], tokens[:, 1]
    if token == "dist":
        return dist
    if token == "mean":
        return 0.5 * (cls + dist)
    return torch.cat([cls, dist], dim=-1)


class DeitDescriptor:
    """Batched raw DeiT descriptors of RGB frames.

    ``features(images) -> float32 [B, feature_dim]`` on the CPU, where ``images`` is uint8 ``[B, 3, H, W]`` /
    ``[3, H, W]`` RGB (a :class:`~pvslam_core.types.Frame`'s ``image``), float in [0, 1], or a list of them.
    """

    def __init__(self, model: VisionTransformer, config: Optional[DeitDescriptorConfig] = None) -> None:
        self.model = model
        self.config = config or DeitDescriptorConfig()
        # fail now, not at the first keyframe, if the token choice needs a distillation token the model lacks
        select_tokens(torch.zeros(1, model.num_prefix_tokens, 1), self.config.token, model.num_prefix_tokens)

    @property
    def feature_dim(self) -> int:
        D = self.model.config.embed_dim
        return 2 * D if self.config.token == "concat" else D

    @property
    def device(self) -> torch.device:
        return self.model.cls_token.device

    def preprocess(self, images: Images) -> torch.Tensor:
        """Normalised model input ``[B, 3, h, w]`` (see :mod:`.preprocess`)."""
        c = self.config
        return preprocess(images, c.input_size, c.resize, CROP_PCT, self.model.config.patch_size)

    def input_size(self, height: int, width: int) -> tuple[int, int]:
        """Model input ``(h, w)`` for a frame of this size."""
        return tuple(self.preprocess(torch.zeros(1, 3, height, width, dtype=torch.uint8)).shape[-2:])  # type: ignore

    def features(self, images: Images) -> torch.Tensor:
        """Raw descriptors (layer-normed token(s), before PCA) ``[B, feature_dim]``, float32, CPU."""
        x = self.preprocess(images)
        model, bs = self.model, self.config.batch_size
        was_training = model.training
        model.eval()
        try:
            with torch.no_grad():  # not inference_mode: its tensors would refuse later autograd / in-place use
                out = [select_tokens(model.forward_tokens(x[i : i + bs].to(self.device)), self.config.token,
                                     model.num_prefix_tokens).float().cpu()
                       for i in range(0, x.shape[0], bs)]
        finally:
            model.train(was_training)
        return torch.cat(out)

    def describe(self, images: Images, projector: Optional[Projector] = None) -> torch.Tensor:
        """Unit descriptors ``[B, d]``: ``L2(projector.transform(features))`` (``L2(features)`` without one)."""
        f = self.features(images)
        return l2_normalize(projector.transform(f) if projector is not None else f)


def build_model(config: Optional[DeitModelConfig] = None) -> tuple[VisionTransformer, Optional[LoadedCheckpoint]]:
    """The model named by a :class:`DeitModelConfig`: loaded strictly from its weights (official or project
    format; the variant must match ``variant``), or a randomly initialised full-size DeiT-base of that variant
    when there are none (:func:`resolve_model_weights`).  Eval mode.  Returns the checkpoint too (its PCA and
    stored settings), None without weights."""
    c = config or DeitModelConfig()
    path = resolve_model_weights(c)
    if path is None:
        ctor = deit_base_distilled_patch16_224 if c.variant == "distilled" else deit_base_patch16_224
        return ctor(pos_embed_antialias=c.pos_embed_antialias).eval(), None
    ck = load_checkpoint(path)
    want = _VARIANT_NAMES[c.variant]
    if ck.model.config.variant != want:
        raise ValueError(f"{path}: a {ck.model.config.variant} DeiT, but variant={c.variant!r} asks for {want}")
    ck.model.pos_embed_antialias = c.pos_embed_antialias
    return ck.model, ck


def make_projector(config: DeitDescriptorConfig, checkpoint_pca: Optional[PCAWhitening] = None
                   ) -> Optional[Projector]:
    """The descriptor projector a config asks for: None, an :class:`OnlinePCA`, or a fixed :class:`PCAWhitening`
    (from ``pca_file``, else the checkpoint's)."""
    if config.pca == "none":
        return None
    if config.pca == "online":
        return OnlinePCA(config.pca_dim, config.whiten, WHITEN_SHRINKAGE, config.pca_min_samples,
                         PCA_REFIT_GROWTH, None)
    if config.pca_file is not None:
        return PCAWhitening.load(config.pca_file)
    if checkpoint_pca is None:
        raise ValueError("pca='fixed' needs pca_file or a project checkpoint that carries a 'pca' entry")
    return checkpoint_pca
