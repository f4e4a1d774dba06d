"""``RaftGruNet``: the ``DroidNet``-like container (``fnet``, ``cnet``, ``update``) with the calls a frontend makes.

Parameter names and shapes equal upstream's ``DroidNet`` (DROID: 102 tensors, 4,002,565 parameters) or PVO's
``DroidNet`` (``variant="pvo"``), so ``load_state_dict(strict=True)`` works on converted checkpoints
(:mod:`.checkpoint`).  Typical use, for ``N`` frames and ``E`` edges ``ii[e] -> jj[e]``::

    feats = model.features(images, channel_order="rgb")        # fmap/net/inp: (B, N, 128, h, w), h = H/8
    corr_fn = model.correlation(feats.fmap, ii, jj)             # CorrVolume (or impl="onthefly")
    coords0 = coords_grid(h, w)                                 # (h, w, 2)
    net, inp = feats.net[:, ii], feats.inp[:, ii]               # per-edge state and context
    for _ in range(iters):
        corr = corr_fn(coords1)                                 # (B, E, 196, h, w)
        motion = droid_motion(coords0, coords1, target)         # (B, E, 4, h, w)
        out = model.update(net, inp, corr, motion, ii, jj)      # UpdateOutput
        net, target, weight = out.net, coords1 + out.delta, out.weight
        ... BA with target, weight, out.eta (frames out.frames) -> new coords1
    disp_up = upsample_disp(disps[:, out.frames], out.upmask)   # (B, U, H, W)

Nothing here runs under ``torch.no_grad`` by itself: inference callers wrap it (and may use autocast on CUDA;
all ops are autocast-friendly and take their constants' dtype from the inputs).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn as nn

from .corr import NUM_LEVELS, RADIUS, CorrVolume, OnTheFlyCorr, check_level_size, make_corr
from .encoders import STRIDE, BasicEncoder, check_image_size, normalize_images
from .update import HIDDEN, VARIANTS, UpdateModule, UpdateOutput

MOTION_CLAMP = 64.0  # upstream clamps the motion input to +-64 (1/8-res pixels)


@dataclass
class Features:
    """Encoder outputs for ``(B, N)`` frames at 1/8 resolution ``h x w``.

    Attributes:
        fmap: ``(B, N, 128, h, w)`` matching features (``fnet``, instance-normalised).
        net: ``(B, N, 128, h, w)`` initial GRU state, ``tanh`` of ``cnet`` channels 0-127 (None if not computed).
        inp: ``(B, N, 128, h, w)`` context, ``relu`` of ``cnet`` channels 128-255 (None if not computed).
    """

    fmap: torch.Tensor
    net: Optional[torch.Tensor] = None
    inp: Optional[torch.Tensor] = None


def droid_motion(coords0: torch.Tensor, coords1: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """DROID motion input ``[coords1 - coords0, target - coords1]``, clamped to +-64.

    ``coords0 (h, w, 2)`` (or broadcastable), ``coords1``, ``target`` ``(B, E, h, w, 2)`` -> ``(B, E, 4, h, w)``.
    """
    motion = torch.cat([coords1 - coords0, target - coords1], dim=-1)
    return motion.permute(0, 1, 4, 2, 3).clamp(-MOTION_CLAMP, MOTION_CLAMP)


def pvo_motion(
    cam_flow: torch.Tensor, delta_dy: torch.Tensor, resd: torch.Tensor, raw_mask: torch.Tensor
) -> torch.Tensor:
    """PVO motion input ``[cam_flow, cam_flow + delta_dy, resd, raw_mask]``, clamped to +-64.

    All ``(B, E, h, w, 2)`` -> ``(B, E, 8, h, w)``.  PVO's training builds ``cam_flow = coords1 - coords0``,
    its inference ``target_cam - coords0``; ``resd = target_cam - coords1``; ``raw_mask`` are the static-mask
    logits (1 = static).
    """
    motion = torch.cat([cam_flow, cam_flow + delta_dy, resd, raw_mask], dim=-1)
    return motion.permute(0, 1, 4, 2, 3).clamp(-MOTION_CLAMP, MOTION_CLAMP)


class RaftGruNet(nn.Module):
    """Encoders + update operator of DROID-SLAM (``variant="droid"``) or PVO (``variant="pvo"``).

    Submodules (state_dict prefixes): ``fnet`` (BasicEncoder 128, instance norm), ``cnet`` (BasicEncoder 256,
    no norm), ``update`` (:class:`.update.UpdateModule`).
    """

    def __init__(self, variant: str = "droid", use_aff_bri: bool = False) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        self.variant, self.use_aff_bri = variant, use_aff_bri
        self.fnet = BasicEncoder(output_dim=128, norm="instance")
        self.cnet = BasicEncoder(output_dim=2 * HIDDEN, norm="none")
        self.update = UpdateModule(variant, use_aff_bri)

    @property
    def motion_dim(self) -> int:
        """Channels of the motion input (4 DROID, 8 PVO)."""
        return self.update.motion_dim

    # --- encoders -------------------------------------------------------------------------------------------
    def _normalized(self, images: torch.Tensor, channel_order: str) -> torch.Tensor:
        check_image_size(*images.shape[-2:])
        check_level_size(images.shape[-2] // STRIDE, images.shape[-1] // STRIDE, NUM_LEVELS)
        return normalize_images(images, channel_order)

    def features(self, images: torch.Tensor, channel_order: str = "bgr", context: bool = True) -> Features:
        """Matching features (and context unless ``context=False``) of ``images (B, N, 3, H, W)``.

        ``images``: uint8 or float in ``[0, 255]``; ``channel_order="bgr"`` as upstream, ``"rgb"`` for pvslam
        frames (:func:`.encoders.frames_to_images`).  ``H, W`` multiples of 8, >= 128.  Equals upstream
        ``extract_features`` (which the motion filter calls with ``context=False`` on every frame).
        """
        x = self._normalized(images, channel_order)
        fmap = self.fnet(x)
        if not context:
            return Features(fmap)
        net, inp = self.split_context(self.cnet(x))
        return Features(fmap, net, inp)

    def context(self, images: torch.Tensor, channel_order: str = "bgr") -> tuple[torch.Tensor, torch.Tensor]:
        """``(net, inp)``, each ``(B, N, 128, h, w)``, of ``images`` (only ``cnet``; e.g. for new keyframes)."""
        return self.split_context(self.cnet(self._normalized(images, channel_order)))

    @staticmethod
    def split_context(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``cnet`` output ``(B, N, 256, h, w)`` -> ``(tanh(c[:, :, :128]), relu(c[:, :, 128:]))``."""
        net, inp = c.split([HIDDEN, HIDDEN], dim=2)
        return torch.tanh(net), torch.relu(inp)

    # --- correlation ----------------------------------------------------------------------------------------
    @staticmethod
    def correlation(
        fmaps: torch.Tensor,
        ii: torch.Tensor,
        jj: torch.Tensor,
        impl: str = "volume",
        num_levels: int = NUM_LEVELS,
        radius: int = RADIUS,
        **kwargs,
    ) -> "CorrVolume | OnTheFlyCorr":
        """Correlation of edges ``ii[e] -> jj[e]`` over per-frame ``fmaps (B, N, 128, h, w)``.

        ``impl="volume"``: :class:`.corr.CorrVolume` (stored pyramid, fast lookups); ``"onthefly"``:
        :class:`.corr.OnTheFlyCorr` (no volume; ``chunk_mb=`` bounds its working memory).  Either object maps
        ``coords1 (B, E, h, w, 2)`` to the lookup ``(B, E, 196, h, w)``.
        """
        return make_corr(fmaps, ii, jj, impl, num_levels, radius, **kwargs)

    # --- update ---------------------------------------------------------------------------------------------
    def forward(
        self,
        net: torch.Tensor,
        inp: torch.Tensor,
        corr: torch.Tensor,
        motion: Optional[torch.Tensor] = None,
        ii: Optional[torch.Tensor] = None,
        jj: Optional[torch.Tensor] = None,
    ) -> UpdateOutput:
        """One update step; see :meth:`.update.UpdateModule.forward` (``model(...)`` == ``model.update(...)``)."""
        return self.update(net, inp, corr, motion, ii, jj)
