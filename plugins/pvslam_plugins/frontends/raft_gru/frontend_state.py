"""State held by the ``raft_gru`` frontend (:mod:`.frontend`): per keyframe, per edge, per-stage timings, and the
network a config asks for.

Kept apart from the frontend's logic so that what is stored, at which resolution and for how long, reads in one
place (the memory budget of a 3000-frame run is the sum of these fields; see the README's "Memory").
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, field
from typing import Any, Optional

import torch

from .config import RaftGruConfig
from .corr import CorrVolume
from .net import RaftGruNet
from .update import GateContext

LOG = logging.getLogger("pvslam.frontend.raft_gru")

DAMPING_INIT = 1e-6  # DROID's FactorGraph.damping buffer starts at 1e-6 for frames never updated


class RandomWeightsWarning(UserWarning):
    """``weights = None``: the network is randomly initialised and its flow is meaningless."""


def cpu_bf16_native() -> bool:
    """Whether this CPU computes bf16 convolutions natively (avx512_bf16 / AMX, through oneDNN).  Without it torch
    runs a bf16 convolution through its reference loops, tens of times slower than fp32."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # pragma: no cover - a torch without the query: fp32 is always right
        return False


def effective_precision(precision: str, device: torch.device) -> str:
    """The arithmetic the network runs in: ``precision``, except bf16 on a CPU without native bf16 runs in fp32
    (logged), so that the CPU profile never makes the network slower than the reference."""
    if precision == "bf16" and device.type == "cpu" and not cpu_bf16_native():
        LOG.warning("raft_gru: this CPU has no native bf16 (avx512_bf16 / AMX): the network runs in fp32")
        return "fp32"
    return precision


def load_network(cfg: RaftGruConfig, device: Any = "cpu") -> RaftGruNet:
    """The network a config asks for (eval mode, on ``device``); see ``RaftGruConfig.weights``."""
    from .checkpoint import load_model

    if cfg.random_weights:
        msg = ("raft_gru: weights = \"random\" -> RANDOMLY INITIALISED network: its flow, weights and poses are "
               "meaningless. Use weights = \"droid\" (`pvslam weights fetch droid`), a checkpoint path, or train one "
               "(`pvslam train frontend --plugin raft_gru`).")
        warnings.warn(msg, RandomWeightsWarning, stacklevel=2)
        LOG.warning(msg)
        return RaftGruNet(cfg.variant or "droid").to(device).eval()
    from pvslam_core.weights import resolve_weights

    path = resolve_weights(cfg.weights)
    model, ckpt = load_model(path, map_location=device, variant=cfg.variant)
    LOG.info("raft_gru: loaded %s network from %s%s", ckpt.variant, path,
             f" ({'; '.join(ckpt.notes)})" if ckpt.notes else "")
    return model


@dataclass
class KeyframeState:
    """One keyframe, keyed by its stable id (features only while it is among the newest ``feature_cache``)."""

    image: torch.Tensor  # uint8 [3, H, W] RGB (to recompute evicted features)
    frame_index: int
    damping: torch.Tensor  # float32 [h, w] learned eta of the last update with this keyframe as a source
    fmap: Optional[torch.Tensor] = None  # [128, h, w] matching features
    net0: Optional[torch.Tensor] = None  # [128, h, w] initial GRU state of its edges
    inp: Optional[torch.Tensor] = None  # [128, h, w] context of its edges
    seg: Optional[torch.Tensor] = None  # int64 [h, w] panoptic ids at the BA resolution
    things: Optional[torch.Tensor] = None  # int64 [K] ids of movable thing segments
    gates: Optional[GateContext] = None  # [1, 384, h, w] its context's share of the GRU gates (edges leaving it)
    filter_gates: Optional[GateContext] = None  # ... plus net0 and zero motion (motion filter; newest keyframe only)
    upmask: Optional[torch.Tensor] = None  # [128, h, w] its last update's aggregated features: the convex-upsampling
    # logits are made from them when needed (RaftGruFrontend._upmask; 128 channels instead of 576)
    disp_up: Optional[torch.Tensor] = None  # float16 [H, W] upsampled inverse depth saved when the mask went
    disp_lo: Optional[torch.Tensor] = None  # float32 [h, w] the inverse depth disp_up was made from

    def nbytes(self) -> int:
        """Bytes held in its tensors."""
        n = sum(_nb(t) for t in (self.image, self.damping, self.fmap, self.net0, self.inp, self.seg, self.things,
                                 self.upmask, self.disp_up, self.disp_lo))
        return n + sum(_nb(g.zrq) + _nb(g.glo) for g in (self.gates, self.filter_gates) if g is not None)


@dataclass
class EdgeState:
    """One edge ``(src id, dst id)``: created at its first observe, dropped when the graph retires it."""

    net: torch.Tensor  # [128, h, w] GRU hidden state
    target: torch.Tensor  # float32 [h, w, 2] (x, y) in the target keyframe
    weight: torch.Tensor  # float32 [h, w, 2] confidence handed to the BA (after eq. 4)
    dynamic: Optional[torch.Tensor] = None  # float32 [h, w] 1 = moving
    raw_mask: Optional[torch.Tensor] = None  # pvo: float32 [h, w, 2] static logits (eq. 6 accumulates here)
    delta_dy: Optional[torch.Tensor] = None  # pvo: float32 [h, w, 2] object flow on dynamic pixels
    corr: Optional[CorrVolume] = None  # corr_impl="volume": this edge's pyramid
    updates: int = 0  # GRU updates this edge received

    def nbytes(self) -> int:
        """Bytes held in its tensors and its correlation volume."""
        n = sum(_nb(t) for t in (self.net, self.target, self.weight, self.dynamic, self.raw_mask, self.delta_dy))
        return n + (self.corr.nbytes() if self.corr is not None else 0)


def _nb(t: Optional[torch.Tensor]) -> int:
    return 0 if t is None else t.numel() * t.element_size()


STAGES = ("track", "fnet", "filter", "cnet", "gates", "reproject", "corr", "update", "weights", "recompute")


@dataclass
class StageStats:
    """Per-stage wall seconds and CPU seconds of the calling thread (``time.thread_time``: with one torch thread
    that is all the work; with more, OpenMP workers' time is not included).  ``fnet`` and ``filter`` are parts of
    ``track``; ``recompute`` includes its own ``fnet``/``cnet``; ``gates`` (the keyframes' :class:`GateContext`, made at
    their first use) is counted inside ``filter`` when the motion filter makes it."""

    seconds: dict = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    cpu: dict = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    counts: dict = field(default_factory=lambda: {k: 0 for k in ("track", "keyframes", "observe", "edge_updates",
                                                                 "edges_returned", "recomputed")})
