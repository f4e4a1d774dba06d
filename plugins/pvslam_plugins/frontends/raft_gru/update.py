"""The update operator: DROID-SLAM's ``UpdateModule`` and PVO's ``DynamicUpdateModule`` as two variants.

Per edge ``e = (ii[e] -> jj[e])``, at 1/8 resolution (``h x w``)::

    corr features   corr_encoder(lookup 196 ch)            1x1 196->128, ReLU, 3x3 128->128, ReLU
    motion features flow_encoder(motion 4 | 8 ch)          7x7 ->128, ReLU, 3x3 128->64, ReLU
    hidden state    net' = ConvGRU(net, [inp 128, corr 128, motion 64])   (global-context gates)
    heads           delta / weight (3x3 128->128, ReLU, 3x3 128->2, GradientClip [, Sigmoid for DROID's weight])
                    PVO only: delta_dy (object flow), delta_mask (mask-logit increment), same layout
    per frame       GraphAgg: edges sharing a source frame are averaged -> eta (damping), upmask (576 logits)

Variants (parameter names equal upstream's, so upstream state_dicts load strictly):

* ``"droid"``: motion = ``[coords1 - coords0, target - coords1]`` (4 ch); ``weight`` is a **sigmoid** confidence;
  graph aggregation's upsampling head is ``agg.upmask``.
* ``"pvo"``: motion = ``[cam_flow, cam_flow + delta_dy, resd, raw_mask]`` (8 ch); ``weight`` is a **raw logit**
  (PVO's callers apply ``sigmoid(w + (1 - static) * 10)``, see ``pvslam_core`` confidence); extra heads
  ``delta_dy`` and ``delta_mask``; the head is named ``agg.upmask_disp``.  ``use_aff_bri`` adds PVO's optional
  photometric-affine head (``global_avg_pool``, ``param_linear``; off in PVO's own scripts).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn as nn

from .corr import lookup_channels

VARIANTS = ("droid", "pvo")
HIDDEN = 128  # GRU state / context width
UPMASK_CHANNELS = 8 * 8 * 9  # convex-upsampling logits: 3x3 neighbours x 8x8 sub-pixels
GRAD_CLIP = 0.01


def motion_channels(variant: str) -> int:
    """Channels of the motion input: 4 (DROID) or 8 (PVO)."""
    return {"droid": 4, "pvo": 8}[variant]


class _GradClip(torch.autograd.Function):
    """Identity forward; backward zeroes gradient entries with ``|g| > 0.01`` or NaN (upstream ``GradClip``)."""

    @staticmethod
    def forward(ctx, x):  # noqa: D401
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        zero = torch.zeros_like(grad)
        grad = torch.where(grad.abs() > GRAD_CLIP, zero, grad)
        return torch.where(torch.isnan(grad), zero, grad)


class GradientClip(nn.Module):
    """Module wrapper of :class:`_GradClip` (no parameters; keeps upstream's Sequential indices)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _GradClip.apply(x)


class ConvGRU(nn.Module):
    """Convolutional GRU with a global context vector added inside the z, r and q gates (DROID's ``ConvGRU``)."""

    def __init__(self, h_planes: int = HIDDEN, i_planes: int = HIDDEN + HIDDEN + 64) -> None:
        super().__init__()
        self.convz = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.convr = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.convq = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.w = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convz_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convr_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convq_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)

    def forward(self, net: torch.Tensor, *inputs: torch.Tensor) -> torch.Tensor:
        """``net (M, 128, h, w)``, inputs concatenated on channels -> new state ``(M, 128, h, w)``."""
        inp = torch.cat(inputs, dim=1)
        net_inp = torch.cat([net, inp], dim=1)
        glo = torch.sigmoid(self.w(net)) * net
        glo = glo.flatten(2).mean(-1)[:, :, None, None]  # spatial mean of the gated state
        z = torch.sigmoid(self.convz(net_inp) + self.convz_glo(glo))
        r = torch.sigmoid(self.convr(net_inp) + self.convr_glo(glo))
        q = torch.tanh(self.convq(torch.cat([r * net, inp], dim=1)) + self.convq_glo(glo))
        return (1 - z) * net + z * q


class GraphAgg(nn.Module):
    """Per-frame damping ``eta`` and upsampling mask from the states of the edges leaving each frame.

    ``conv1 + ReLU`` per edge; mean over edges with the same source ``ii`` (frames in ascending order, as
    ``torch.unique(sorted=True)`` + ``scatter_mean``); ``conv2 + ReLU``; ``eta = 0.01 * softplus(conv)``,
    ``upmask = conv1x1 -> 576``.
    """

    def __init__(self, upmask_name: str = "upmask") -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(HIDDEN, HIDDEN, 3, padding=1)
        self.conv2 = nn.Conv2d(HIDDEN, HIDDEN, 3, padding=1)
        self.relu = nn.ReLU(inplace=True)
        self.eta = nn.Sequential(nn.Conv2d(HIDDEN, 1, 3, padding=1), GradientClip(), nn.Softplus())
        self.upmask_name = upmask_name
        self.add_module(upmask_name, nn.Sequential(nn.Conv2d(HIDDEN, UPMASK_CHANNELS, 1, padding=0)))

    def forward(self, net: torch.Tensor, ii: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``net (B, E, 128, h, w)``, ``ii (E,)`` -> ``eta (B, U, h, w)``, ``upmask (B, U, 576, h, w)``,
        ``frames (U,)``.

        ``frames`` are the sorted unique source indices; map ``u`` of the outputs belongs to frame ``frames[u]``.
        """
        b, e, ch, h, w = net.shape
        frames, ix = torch.unique(ii.to(net.device), sorted=True, return_inverse=True)
        u = frames.numel()
        x = self.relu(self.conv1(net.reshape(b * e, ch, h, w))).reshape(b, e, HIDDEN, h, w)
        summed = x.new_zeros(b, u, HIDDEN, h, w).index_add_(1, ix, x)
        count = torch.bincount(ix, minlength=u).clamp_(min=1).to(x.dtype)
        x = (summed / count.reshape(1, u, 1, 1, 1)).reshape(b * u, HIDDEN, h, w)
        x = self.relu(self.conv2(x))
        eta = self.eta(x).reshape(b, u, h, w)
        upmask = getattr(self, self.upmask_name)(x).reshape(b, u, UPMASK_CHANNELS, h, w)
        return 0.01 * eta, upmask, frames


def _head(out: int = 2, sigmoid: bool = False) -> nn.Sequential:
    layers = [nn.Conv2d(HIDDEN, HIDDEN, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(HIDDEN, out, 3, padding=1),
              GradientClip()]
    if sigmoid:
        layers.append(nn.Sigmoid())
    return nn.Sequential(*layers)


@dataclass
class UpdateOutput:
    """Result of one update step for ``E`` edges (``B`` batch, ``h x w`` = 1/8 resolution, ``U`` unique sources).

    Attributes:
        net: ``(B, E, 128, h, w)`` new GRU hidden state per edge.
        delta: ``(B, E, h, w, 2)`` flow revision ``(du, dv)`` in 1/8-res pixels; the BA target is
            ``coords1 + delta``.  For PVO this is the *camera* (static) part.
        weight: ``(B, E, h, w, 2)`` per-coordinate confidence: DROID a sigmoid in (0, 1); PVO a **raw logit**
            (``weight_is_logit``) to be turned into a confidence with the panoptic-aware sigmoid.
        eta: ``(B, U, h, w)`` per-frame depth damping ``0.01 * softplus``; ``None`` when no ``ii`` was given.
        upmask: ``(B, U, 576, h, w)`` convex-upsampling logits per frame (:func:`.upsample.upsample_disp`);
            PVO's ``upmask['disp']``.  ``None`` without ``ii``.
        frames: ``(U,)`` sorted unique ``ii``: ``eta[:, u]`` and ``upmask[:, u]`` belong to frame ``frames[u]``.
        delta_dy: PVO only, ``(B, E, h, w, 2)`` dynamic (object) flow increment.
        delta_m: PVO only, ``(B, E, h, w, 2)`` increment of the raw static-mask logits (1 = static in PVO).
        aff_params: PVO with ``use_aff_bri`` only, ``(B, E, 2)`` photometric affine parameters in (0, 1).
        weight_is_logit: True for PVO.
    """

    net: torch.Tensor
    delta: torch.Tensor
    weight: torch.Tensor
    eta: Optional[torch.Tensor] = None
    upmask: Optional[torch.Tensor] = None
    frames: Optional[torch.Tensor] = None
    delta_dy: Optional[torch.Tensor] = None
    delta_m: Optional[torch.Tensor] = None
    aff_params: Optional[torch.Tensor] = None
    weight_is_logit: bool = False

    def as_upstream(self) -> tuple:
        """The tuple upstream's module returns (for comparisons): DROID ``(net, delta, weight[, eta, upmask])``;
        PVO ``(net, cat[delta, delta_dy], weight, eta, {'disp': upmask, 'flow': None, 'dy_mask': None}, delta_m
        [, aff_params])`` or ``(net, delta4, weight, delta_m)`` without ii."""
        if self.delta_dy is None:
            head = (self.net, self.delta, self.weight)
            return head if self.eta is None else head + (self.eta, self.upmask)
        delta4 = torch.cat([self.delta, self.delta_dy], dim=-1)
        if self.eta is None:
            return (self.net, delta4, self.weight, self.delta_m)
        out = (self.net, delta4, self.weight, self.eta, {"disp": self.upmask, "flow": None, "dy_mask": None},
               self.delta_m)
        return out + ((self.aff_params,) if self.aff_params is not None else ())


class UpdateModule(nn.Module):
    """DROID ``UpdateModule`` (``variant="droid"``) or PVO ``DynamicUpdateModule`` (``variant="pvo"``)."""

    def __init__(self, variant: str = "droid", use_aff_bri: bool = False) -> None:
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        if use_aff_bri and variant != "pvo":
            raise ValueError("use_aff_bri exists only for the 'pvo' variant")
        self.variant, self.use_aff_bri = variant, use_aff_bri
        self.motion_dim = motion_channels(variant)
        pvo = variant == "pvo"
        # Attribute order = upstream's state_dict order.
        self.corr_encoder = nn.Sequential(
            nn.Conv2d(lookup_channels(), HIDDEN, 1, padding=0), nn.ReLU(inplace=True),
            nn.Conv2d(HIDDEN, HIDDEN, 3, padding=1), nn.ReLU(inplace=True))
        self.flow_encoder = nn.Sequential(
            nn.Conv2d(self.motion_dim, HIDDEN, 7, padding=3), nn.ReLU(inplace=True),
            nn.Conv2d(HIDDEN, 64, 3, padding=1), nn.ReLU(inplace=True))
        self.weight = _head(sigmoid=not pvo)  # PVO: no Sigmoid at the end (raw logits)
        self.delta = _head()
        if pvo:
            self.delta_dy = _head()
            self.delta_mask = _head()
        if use_aff_bri:
            self.global_avg_pool = nn.Sequential(
                nn.Conv2d(HIDDEN, HIDDEN, 3, padding=1), nn.ReLU(inplace=True), nn.AdaptiveAvgPool2d((1, 1)),
                GradientClip())
            self.param_linear = nn.Sequential(nn.Linear(HIDDEN, 2), nn.Sigmoid())
        self.gru = ConvGRU(HIDDEN, HIDDEN + HIDDEN + 64)
        self.agg = GraphAgg("upmask_disp" if pvo else "upmask")

    def forward(
        self,
        net: torch.Tensor,
        inp: torch.Tensor,
        corr: torch.Tensor,
        motion: Optional[torch.Tensor] = None,
        ii: Optional[torch.Tensor] = None,
        jj: Optional[torch.Tensor] = None,
    ) -> UpdateOutput:
        """One update step.

        Args:
            net: ``(B, E, 128, h, w)`` GRU state per edge (initially ``tanh`` context of the source frame).
            inp: ``(B, E, 128, h, w)`` context per edge (``relu`` context of the source frame).
            corr: ``(B, E, 196, h, w)`` correlation lookup at ``coords1``.
            motion: ``(B, E, 4 | 8, h, w)`` motion input (see :func:`.net.droid_motion` / :func:`.net.pvo_motion`);
                zeros when None (as upstream).
            ii: ``(E,)`` source frame of each edge; enables graph aggregation (``eta``, ``upmask``).
            jj: unused by the network (kept for upstream's signature).
        """
        b, e, ch, h, w = net.shape
        for name, t, c in (("inp", inp, HIDDEN), ("corr", corr, lookup_channels())):
            if t.shape != (b, e, c, h, w):
                raise ValueError(f"{name} must be {(b, e, c, h, w)}, got {tuple(t.shape)}")
        if motion is None:
            motion = net.new_zeros(b, e, self.motion_dim, h, w)
        elif motion.shape != (b, e, self.motion_dim, h, w):
            raise ValueError(
                f"motion must be {(b, e, self.motion_dim, h, w)} for variant {self.variant!r}, "
                f"got {tuple(motion.shape)}"
            )
        m = b * e
        corr_f = self.corr_encoder(corr.reshape(m, -1, h, w))
        flow_f = self.flow_encoder(motion.reshape(m, -1, h, w))
        net = self.gru(net.reshape(m, ch, h, w), inp.reshape(m, -1, h, w), corr_f, flow_f)

        def chan_last(head: nn.Module) -> torch.Tensor:  # (M, 2, h, w) -> (B, E, h, w, 2)
            return head(net).reshape(b, e, -1, h, w).permute(0, 1, 3, 4, 2)[..., :2].contiguous()

        extra: dict = {}
        if self.variant == "pvo":
            extra.update(delta_dy=chan_last(self.delta_dy), delta_m=chan_last(self.delta_mask), weight_is_logit=True)
            if self.use_aff_bri:
                extra["aff_params"] = self.param_linear(self.global_avg_pool(net).reshape(m, -1)).reshape(b, e, -1)
        delta, weight = chan_last(self.delta), chan_last(self.weight)
        net = net.reshape(b, e, ch, h, w)
        if ii is not None:
            if ii.numel() != e:
                raise ValueError(f"ii has {ii.numel()} entries for {e} edges")
            extra["eta"], extra["upmask"], extra["frames"] = self.agg(net, ii)
        return UpdateOutput(net=net, delta=delta, weight=weight, **extra)
