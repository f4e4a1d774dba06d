"""The DIS flows of a pair of gray images and what the bundle adjustment gets from them: BA targets and confidences.

Confidence of a pixel = ``exp(-fb^2 / 2 sigma^2)`` (forward-backward consistency, 0 where ``x + f(x)`` leaves the
image) x ``exp(-r^2 / 2 sigma_p^2)`` (local photometric residual after the exposure change) x ``lam / (lam + tau)``
(texture of the source image, Shi-Tomasi), pooled over each BA block.  Why three terms: the forward-backward check
misses flows that are wrong the same way in both directions, the photometric one those that also look plausible,
and on weak texture (the near road at speed, bare walls, the flanks of buses) DIS is wrong in exactly that way, so
only the texture itself tells.

:class:`FlowPairs` owns the DIS objects (:class:`.lanes.DisLanes`: one per kind of call and thread, so that a
flow depends on its inputs alone) and the texture term of each source image, computed once.  Flows are at the flow
resolution (``dis.scale`` of the image), ``float32 [H, W, 2]``; targets ``[2, h, w]`` and weights ``[h, w]`` at the
BA resolution.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import numpy as np

from . import flow_ops as F
from .config import DisConfig
from .lanes import Call, DisLanes

FB_SIGMA = 1.0  # forward-backward consistency scale (full-resolution px): c = exp(-fb^2 / (2 sigma^2))
FB_FAIL_PX = 3.0  # a pixel fails the forward-backward check when fb exceeds this (full-resolution px)
PHOTO_SIGMA = 4.0  # photometric confidence scale (gray levels); 0: off (docs/decisions.md: PHOTO_SIGMA)
# texture term lam / (lam + tau), lam the Shi-Tomasi eigenvalue (OpenCV's scale: ~1e-4 on fine asphalt, 1e-3 on
# facades); 0 would switch it off (docs/decisions.md: TEXTURE_TAU)
TEXTURE_TAU = 1e-3
# ... tau is at most this quantile of the image's own lam, so an image weak everywhere (a bare room) keeps relative
# weights instead of all falling below the confidence thresholds downstream
TEXTURE_QUANTILE = 0.75
WEIGHTED_POOLING = True  # a BA block's flow is the confidence-weighted mean of its pixels' (robust at occlusions)

Plane = Optional[tuple[np.ndarray, np.ndarray]]  # (bool mask [H, W], weight float32 [H, W]) of the road plane's pixels


class FlowPairs:
    """DIS flows of image pairs on ``dis.threads`` threads, and their BA targets and confidences."""

    def __init__(self, dis: DisConfig):
        self.scale = float(dis.scale)
        preset, finest = dis.preset, dis.finest_scale
        # Calls with an initial flow get their own DIS object: after such a call, OpenCV's DIS keeps using that
        # initial flow in later calls without one (OpenCV 4.x/5.0), so the zero-init flows (tracking, close edges)
        # would depend on whichever edge was initialised last.  lanes.py keeps one object per kind of call and
        # thread (flow_ops.create_dis is looked up at creation, so a test can replace it).
        self.lanes = DisLanes(lambda kind: F.create_dis(preset, finest_scale=finest), threads=dis.threads)
        self._texture = F.TextureTerm(TEXTURE_TAU, TEXTURE_QUANTILE) if TEXTURE_TAU > 0 else None
        self.stats = {"dis_calls": 0, "dis_s": 0.0}

    @property
    def sigma(self) -> float:
        """The forward-backward scale at the flow resolution (px)."""
        return FB_SIGMA * self.scale

    @property
    def fail_px(self) -> float:
        """A flow-resolution forward-backward error above this fails the check (px)."""
        return FB_FAIL_PX * self.scale

    def fail_fraction(self, fb: np.ndarray) -> float:
        """Fraction of the pixels whose forward-backward error ``fb`` fails the check (inf: left the image)."""
        return float(np.mean(~(fb <= self.fail_px)))

    def gray(self, image) -> np.ndarray:
        """uint8 ``[H, W]`` gray image at the flow resolution of a frame's ``uint8 [3, H, W]`` image."""
        return F.to_gray(image, self.scale)

    # --------------------------------------------------------------------------------------- DIS calls --
    @staticmethod
    def pair_calls(g0: np.ndarray, g1: np.ndarray, init_f: Optional[np.ndarray] = None,
                   init_b: Optional[np.ndarray] = None, kind: str = "edge") -> list[Call]:
        """The forward and backward DIS calls between two grays (with initial flows: ``kind + "_init"``)."""
        k = kind + ("_init" if init_f is not None else "")
        return [(k, g0, g1, init_f), (k, g1, g0, init_b)]

    def flows(self, calls: Sequence[Call]) -> list[np.ndarray]:
        """DIS flows of independent ``(kind, i0, i1, init)`` calls (lanes.py: on ``dis.threads`` threads)."""
        flows, seconds = self.lanes.run(calls)
        self.count(len(calls), seconds)
        return flows

    def flow(self, kind: str, i0: np.ndarray, i1: np.ndarray, init: Optional[np.ndarray] = None) -> np.ndarray:
        return self.flows([(kind, i0, i1, init)])[0]

    def map(self, fn: Callable, items: Sequence) -> list:
        """``[fn(item) for item in items]`` spread over the lanes (``fn`` may call :meth:`lane_flow`)."""
        return self.lanes.map(fn, items)

    def lane_flow(self, call: Call) -> tuple[np.ndarray, float]:
        """One DIS call on the calling thread's object for its kind: the flow and its seconds (not counted)."""
        return self.lanes.flow(call)

    def count(self, calls: int, seconds: float) -> None:
        """Add DIS calls made through :meth:`map` / :meth:`lane_flow` to the statistics."""
        self.stats["dis_calls"] += calls
        self.stats["dis_s"] += seconds

    def close(self) -> None:
        self.lanes.close()

    # ---------------------------------------------------------------------------- targets, confidence --
    def direction(self, g0: np.ndarray, g1: np.ndarray, fwd: np.ndarray, bwd: np.ndarray, h: int, w: int,
                  plane: Plane = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """BA target ``[2, h, w]``, confidence ``[h, w]`` and forward-backward error ``[H, W]`` of the flow
        ``g0 -> g1`` (``fwd``), checked against ``bwd``.  ``plane``: pixels whose flow is the road plane's and their
        verification weight, which stands in for the texture term there (that term is for DIS's mistakes on weak
        texture, and the road's texture is weak)."""
        conf, fb = F.fb_consistency(fwd, bwd, self.sigma)
        if PHOTO_SIGMA > 0:
            conf = conf * F.photometric_confidence(g0, g1, fwd, PHOTO_SIGMA)
        if self._texture is not None:
            tex = self._texture(g0)
            conf = conf * (tex if plane is None else np.where(plane[0], plane[1], tex))
        elif plane is not None:
            conf = conf * np.where(plane[0], plane[1], np.float32(1.0))
        t, wgt = F.pool_to_ba(fwd, conf, h, w, WEIGHTED_POOLING)
        return t, wgt, fb

    def nbytes(self) -> int:
        """Bytes held by the texture terms of recent source images."""
        return 0 if self._texture is None else self._texture.nbytes()
