"""The update operator: DROID-SLAM's ``UpdateModule`` and PVO's ``DynamicUpdateModule`` as two variants.

Per edge ``e = (ii[e] -> jj[e])``, at 1/8 resolution (``h x w``)::

    corr features   corr_encoder(lookup 196 ch)            1x1 196 to 128 ch, ReLU, 3x3 128 to 128, ReLU
    motion features flow_encoder(motion 4 | 8 ch)          7x7 to 128 ch, ReLU, 3x3 128 to 64, ReLU
    hidden state    net' = ConvGRU(net, [inp 128, corr 128, motion 64])   (global-context gates)
    heads           delta / weight (3x3 128 to 128, ReLU, 3x3 128 to 2, GradientClip [, Sigmoid for DROID's weight])
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
import torch.nn.functional as F

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


def _cat(tensors: list[torch.Tensor]) -> torch.Tensor:
    """Channel concatenation in the autocast dtype when autocast is on: the convolution that follows would cast the
    result to it anyway (same values), and a mixed bf16/fp32 list would otherwise be promoted to an fp32 copy that
    is then cast back, a noticeable share of the frontend's time on a CPU."""
    dev = tensors[0].device.type
    if torch.is_autocast_enabled(dev):
        dt = torch.get_autocast_dtype(dev)
        tensors = [t.to(dt) for t in tensors]
    return torch.cat(tensors, dim=1)


# Input blocks of the gate convolutions, in channel order: convz / convr see [net | inp | corr | motion], convq sees
# [r * net | inp | corr | motion] (DROID: 128 + 128 + 128 + 64 = 448 channels).
GATE_INPUTS = ("net", "inp", "corr", "motion")


@dataclass
class GateContext:
    """The constant part of the ConvGRU gate pre-activations of ``M`` edges (:meth:`ConvGRU.context`).

    A gate convolution is linear in its input channels, so ``conv([net, inp, corr, motion])`` is the sum of the
    convolutions of each block with its slice of the weights.  Blocks that do not change between updates - the
    context ``inp`` of an edge's source keyframe always; for the motion filter's single step also the state ``net0``
    and the zero-motion features - are convolved once (per keyframe) and stored here with the biases; each update
    then convolves only the changing blocks (320 of 448 input channels for an edge, 128 for the motion filter).
    Same function, other rounding (fp32: ~1e-6, tests/test_fast_paths.py).

    Attributes:
        zrq: ``(M, 3*128, h, w)`` ``[z | r | q]`` biases + convolutions of the constant blocks.
        const: the constant blocks folded into ``zrq`` (names of :data:`GATE_INPUTS`; the ``net`` block of ``q`` is
            ``r * net`` and never constant).
        glo: ``(M, 3*128, 1, 1)`` the global-context terms ``[z | r | q]`` when ``net`` is constant, else None.
        groups: optional run lengths: ``zrq`` then holds one row per run of consecutive edges sharing it (e.g. the
            edges of one source keyframe, sorted by source), added in place per run instead of being copied per
            edge (``sum(groups) = M``; ``glo`` must be None).
    """

    zrq: torch.Tensor
    const: tuple[str, ...]
    glo: Optional[torch.Tensor] = None
    groups: Optional[list[int]] = None

    def __post_init__(self) -> None:
        if self.groups is not None and (self.glo is not None or len(self.groups) != self.zrq.shape[0]):
            raise ValueError(f"GateContext: {len(self.groups)} groups for {self.zrq.shape[0]} context rows "
                             f"(and glo must be None with groups)")

    @property
    def rows(self) -> int:
        """Edges ``M`` this context is for."""
        return self.zrq.shape[0] if self.groups is None else sum(self.groups)

    def add_to(self, x: torch.Tensor, chans: slice) -> torch.Tensor:
        """``x + zrq[:, chans]`` (per run with ``groups``), in the wider of the two dtypes."""
        part = self.zrq[:, chans]
        if self.groups is None:
            return x + part
        x = x.to(torch.promote_types(x.dtype, part.dtype))  # a copy only when x is 16-bit: x is not modified
        start = 0
        for u, n in enumerate(self.groups):
            x[start:start + n].add_(part[u])
            start += n
        return x


class ConvGRU(nn.Module):
    """Convolutional GRU with a global context vector added inside the z, r and q gates (DROID's ``ConvGRU``).

    :meth:`forward` is upstream's computation; :meth:`context` + :meth:`forward_context` compute the same update
    with the constant input blocks convolved once (:class:`GateContext`).
    """

    def __init__(self, h_planes: int = HIDDEN, i_planes: int = HIDDEN + HIDDEN + 64,
                 blocks: tuple[int, ...] = (HIDDEN, HIDDEN, 64)) -> None:
        super().__init__()
        self.convz = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.convr = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.convq = nn.Conv2d(h_planes + i_planes, h_planes, 3, padding=1)
        self.w = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convz_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convr_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        self.convq_glo = nn.Conv2d(h_planes, h_planes, 1, padding=0)
        if sum(blocks) != i_planes:
            raise ValueError(f"input blocks {blocks} do not add up to i_planes={i_planes}")
        edges = [0, h_planes]
        for b in blocks:
            edges.append(edges[-1] + b)
        self._blocks = {n: slice(a, b) for n, a, b in zip(GATE_INPUTS, edges[:-1], edges[1:])}
        self._wcache: dict = {}  # sliced gate weights of forward_context (not parameters, not in the state_dict)

    def forward(self, net: torch.Tensor, *inputs: torch.Tensor) -> torch.Tensor:
        """``net (M, 128, h, w)``, inputs concatenated on channels -> new state ``(M, 128, h, w)``."""
        inp = _cat(list(inputs))
        net_inp = _cat([net, inp])
        glo = torch.sigmoid(self.w(net)) * net
        glo = glo.flatten(2).mean(-1)[:, :, None, None]  # spatial mean of the gated state
        z = torch.sigmoid(self.convz(net_inp) + self.convz_glo(glo))
        r = torch.sigmoid(self.convr(net_inp) + self.convr_glo(glo))
        q = torch.tanh(self.convq(_cat([r * net, inp])) + self.convq_glo(glo))
        return (1 - z) * net + z * q

    # --- the same update with constant input blocks precomputed -------------------------------------------------
    def _gate_weight(self, gates: str, names: tuple[str, ...], like: torch.Tensor) -> torch.Tensor:
        """``[convz; convr]`` (``gates="zr"``) or ``convq`` weights restricted to input blocks ``names``; cached per
        dtype (the autocast dtype when autocast is on, so that it is not re-cast at every call) and invalidated
        when a parameter changes."""
        convs = (self.convz, self.convr) if gates == "zr" else (self.convq,)
        dev = like.device.type
        dt = torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else like.dtype
        key = (gates, names, dt, like.device)
        stamp = tuple((c.weight.data_ptr(), c.weight._version) for c in convs)
        hit = self._wcache.get(key)
        if hit is not None and hit[0] == stamp and not torch.is_grad_enabled():
            return hit[1]
        w = torch.cat([torch.cat([c.weight[:, self._blocks[n]] for n in names], dim=1) for c in convs], dim=0)
        if torch.is_grad_enabled() and any(c.weight.requires_grad for c in convs):
            return w.to(dt)  # differentiable, not cached
        w = w.detach().to(dt)
        self._wcache[key] = (stamp, w)
        return w

    def _glo_terms(self, net: torch.Tensor) -> torch.Tensor:
        """``[z | r | q]`` global-context terms ``(M, 3*128, 1, 1)`` of state ``net``."""
        glo = torch.sigmoid(self.w(net)) * net
        glo = glo.flatten(2).mean(-1)[:, :, None, None]
        return torch.cat([self.convz_glo(glo), self.convr_glo(glo), self.convq_glo(glo)], dim=1)

    def context(self, bias: bool = True, **blocks: torch.Tensor) -> GateContext:
        """The :class:`GateContext` of constant input blocks, e.g. ``context(inp=inp)`` or ``context(net=net0,
        inp=inp, motion=flow_features)`` (each ``(M, C_block, h, w)``).  ``bias=False``: only the blocks' share
        (contexts are additive: ``context(inp=a).zrq + context(False, net=b).zrq`` = ``context(inp=a, net=b).zrq``
        to float rounding)."""
        names = tuple(n for n in GATE_INPUTS if n in blocks)
        if not names or set(blocks) - set(names):
            raise ValueError(f"context blocks must be among {GATE_INPUTS}, got {sorted(blocks)}")
        ref = blocks[names[0]]
        zr = F.conv2d(_cat([blocks[n] for n in names]), self._gate_weight("zr", names, ref), padding=1)
        if bias:
            zr = zr + torch.cat([self.convz.bias, self.convr.bias])[:, None, None]
        qn = tuple(n for n in names if n != "net")
        if qn:
            q = F.conv2d(_cat([blocks[n] for n in qn]), self._gate_weight("q", qn, ref), padding=1)
            q = q + self.convq.bias[:, None, None] if bias else q
        else:
            q = self.convq.bias[None, :, None, None] if bias else zr.new_zeros(1, zr.shape[1] // 2, 1, 1)
            q = q.expand(zr.shape[0], -1, *zr.shape[-2:]).to(zr.dtype)
        glo = self._glo_terms(blocks["net"]) if "net" in blocks else None
        return GateContext(torch.cat([zr, q.to(zr.dtype)], dim=1), names, glo)

    def forward_context(self, net: torch.Tensor, ctx: GateContext, **blocks: torch.Tensor) -> torch.Tensor:
        """The update of :meth:`forward` from the changing input blocks (``corr=``, and ``motion=`` unless it is in
        ``ctx``) and the constant ones' :class:`GateContext`."""
        var = tuple(n for n in GATE_INPUTS if n not in ctx.const)
        xs = dict(blocks, net=net)
        missing = [n for n in var if xs.get(n) is None]
        if missing:
            raise ValueError(f"forward_context needs the changing blocks {missing} (context has {ctx.const})")
        hp = net.shape[1]
        if ctx.rows != net.shape[0]:
            raise ValueError(f"the gate context is for {ctx.rows} edges, net has {net.shape[0]}")
        zr = ctx.add_to(F.conv2d(_cat([xs[n] for n in var]), self._gate_weight("zr", var, net), padding=1),
                        slice(0, 2 * hp))
        glo = ctx.glo if ctx.glo is not None else self._glo_terms(net)
        zr = torch.sigmoid(zr + glo[:, :2 * hp])  # z and r in one pass
        z, r = zr[:, :hp], zr[:, hp:]
        qv = ("net",) + tuple(n for n in var if n != "net")
        xq = _cat([r * net] + [xs[n] for n in qv[1:]])
        q = F.conv2d(xq, self._gate_weight("q", qv, net), padding=1)
        q = ctx.add_to(q, slice(2 * hp, 3 * hp)) + glo[:, 2 * hp:]
        # tanh(x) = 2 sigmoid(2x) - 1 (fp32 torch.tanh is ~5x slower than sigmoid on this CPU), and the GRU blend
        # (1 - z) net + z q written as lerp(net, q, z): one pass instead of four; both differ by fp32 rounding only
        q = torch.sigmoid(2 * q).mul_(2).sub_(1)
        return torch.lerp(net.to(q.dtype), q, z.to(q.dtype))


class GraphAgg(nn.Module):
    """Per-frame damping ``eta`` and upsampling mask from the states of the edges leaving each frame.

    ``conv1 + ReLU`` per edge; mean over edges with the same source ``ii`` (frames in ascending order, as
    ``torch.unique(sorted=True)`` + ``scatter_mean``); ``conv2 + ReLU``; ``eta = 0.01 * softplus(conv)``,
    ``upmask = conv1x1`` to 576 channels.
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
        eta, x, frames = self.eta_features(net, ii)
        return eta, self.upmask_of(x), frames

    def eta_features(self, net: torch.Tensor, ii: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`forward` without the upsampling head: ``eta (B, U, h, w)``, the aggregated features ``(B, U, 128,
        h, w)`` that :meth:`upmask_of` turns into the mask, ``frames (U,)`` (a frontend keeps the 128 features of a
        keyframe's last update and makes its 576-channel mask only when it upsamples)."""
        b, e, ch, h, w = net.shape
        frames, ix = torch.unique(ii.to(net.device), sorted=True, return_inverse=True)
        u = frames.numel()
        x = self.relu(self.conv1(net.reshape(b * e, ch, h, w))).reshape(b, e, HIDDEN, h, w)
        summed = x.new_zeros(b, u, HIDDEN, h, w).index_add_(1, ix, x)
        count = torch.bincount(ix, minlength=u).clamp_(min=1).to(x.dtype)
        x = (summed / count.reshape(1, u, 1, 1, 1)).reshape(b * u, HIDDEN, h, w)
        x = self.relu(self.conv2(x))
        eta = self.eta(x).reshape(b, u, h, w)
        return 0.01 * eta, x.reshape(b, u, HIDDEN, h, w), frames

    def upmask_of(self, feats: torch.Tensor) -> torch.Tensor:
        """Upsampling logits ``(B, U, 576, h, w)`` from :meth:`eta_features`' ``(B, U, 128, h, w)``."""
        b, u, ch, h, w = feats.shape
        return getattr(self, self.upmask_name)(feats.reshape(b * u, ch, h, w)).reshape(b, u, UPMASK_CHANNELS, h, w)


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
        agg_features: ``(B, U, 128, h, w)`` only with ``upmask=False``: what ``upmask`` would be made from
            (:meth:`GraphAgg.upmask_of`); ``upmask`` is then None.
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
    agg_features: Optional[torch.Tensor] = None

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
        ctx: Optional[GateContext] = None,
        upmask: bool = True,
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
            ctx: optional :class:`GateContext` of the ``B*E`` edges (:meth:`gate_context`): the same update with the
                constant input blocks precomputed; ``inp`` (and ``motion`` when the context holds it) is then not
                used and may be None.
            upmask: False = skip the upsampling head; ``agg_features`` holds its input instead.
        """
        b, e, ch, h, w = net.shape
        checks = [("corr", corr, lookup_channels())]
        if ctx is None or "inp" not in ctx.const:
            checks.append(("inp", inp, HIDDEN))
        for name, t, c in checks:
            if t is None or t.shape != (b, e, c, h, w):
                raise ValueError(f"{name} must be {(b, e, c, h, w)}, got {None if t is None else tuple(t.shape)}")
        const_motion = ctx is not None and "motion" in ctx.const
        if motion is None and not const_motion:
            motion = net.new_zeros(b, e, self.motion_dim, h, w)
        elif motion is not None and motion.shape != (b, e, self.motion_dim, h, w):
            raise ValueError(
                f"motion must be {(b, e, self.motion_dim, h, w)} for variant {self.variant!r}, "
                f"got {tuple(motion.shape)}"
            )
        m = b * e
        corr_f = self.corr_encoder(corr.reshape(m, -1, h, w))
        if ctx is None:
            flow_f = self.flow_encoder(motion.reshape(m, -1, h, w))
            net = self.gru(net.reshape(m, ch, h, w), inp.reshape(m, -1, h, w), corr_f, flow_f)
        else:
            if ctx.rows != m:
                raise ValueError(f"ctx holds {ctx.rows} edges, the update {m}")
            blocks = {"corr": corr_f}
            if not const_motion:
                blocks["motion"] = self.flow_encoder(motion.reshape(m, -1, h, w))
            if "inp" not in ctx.const:
                blocks["inp"] = inp.reshape(m, -1, h, w)
            net = self.gru.forward_context(net.reshape(m, ch, h, w), ctx, **blocks)

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
            if upmask:
                extra["eta"], extra["upmask"], extra["frames"] = self.agg(net, ii)
            else:
                extra["eta"], extra["agg_features"], extra["frames"] = self.agg.eta_features(net, ii)
        return UpdateOutput(net=net, delta=delta, weight=weight, **extra)

    def gate_context(self, inp: torch.Tensor, net: Optional[torch.Tensor] = None,
                     zero_motion: bool = False) -> GateContext:
        """:class:`GateContext` of frames' context ``inp (M, 128, h, w)`` - what every edge leaving those frames
        shares - and, for a first update from the frames' own state ``net (M, 128, h, w)`` with no motion input
        (``zero_motion``: upstream's motion filter), also of ``net`` and the zero motion's features."""
        blocks = {"inp": inp}
        if net is not None:
            blocks["net"] = net
        if zero_motion:
            m, _, h, w = inp.shape
            blocks["motion"] = self.flow_encoder(inp.new_zeros(m, self.motion_dim, h, w))
        return self.gru.context(**blocks)
