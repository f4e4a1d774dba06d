"""The ``deit`` loop detector: DeiT global descriptors (eq. 12), cosine retrieval (eq. 8), optional verification.

Per keyframe (stable id, in time order)::

    add_keyframe(id, frame)   buffer the frame (and store it for verification); describe the buffer when it holds
                              batch_size keyframes
    query(id, skip)           describe what is still buffered (one batched forward pass), then retrieve older
                              keyframes outside the temporal exclusion with cosine >= threshold, best first;
                              verify them with the shared module when verify = true (verified True/False), else
                              return them as retrieval-only candidates (verified = None)
    on_keyframe_removed(id)   forget it (buffer, descriptor index, verification store)

The mapper queries every keyframe right after its window BA, so in the pipeline a forward pass usually holds one
keyframe; callers that add several keyframes before querying (offline evaluation, training) get full batches.
Acceptance (consecutive hits, suppression near accepted loops, orientation) is the mapper's loop policy.
"""
from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Optional

import torch

from pvslam_core.interfaces import LoopDetector
from pvslam_core.types import Frame, LoopCandidate

from ..verification import KeyframeVerifier, Verification
from .config import DeitLoopConfig, with_checkpoint
from .descriptor import DeitDescriptor, build_model, make_projector
from .retrieval import LoopRetrieval

LOG = logging.getLogger("pvslam")


class UntrainedDeitWarning(UserWarning):
    """The detector runs on randomly initialised weights: its loop candidates carry no information."""


@dataclass
class _Pending:
    kf_id: int
    image: torch.Tensor  # uint8 [3, H, W]
    timestamp: float


class DeitLoopDetector(LoopDetector):
    """Keyframe database of DeiT descriptors (see the module docstring).

    ``weights`` of the config decides the model: the shipped checkpoint by default (``"builtin"``), an official or
    project checkpoint, or none (random init, with an :class:`UntrainedDeitWarning`).  A project checkpoint's
    stored settings (input size, token, PCA, threshold it was calibrated with) replace the defaults of the fields
    not set in the config; the effective config is ``self.config``.
    """

    def __init__(self, config: Optional[DeitLoopConfig] = None, device: Optional[str | torch.device] = None
                 ) -> None:
        config = config or DeitLoopConfig()
        model, ck = build_model(config)
        if device is not None:
            model = model.to(device)
        if ck is not None and ck.descriptor:
            config = with_checkpoint(config, ck.descriptor)
        self.config = config
        self.checkpoint = ck
        self.trained = ck is not None
        if not self.trained:
            msg = (f"deit loop detector: no trained weights (weights = {config.weights!r}, variant "
                   f"{config.variant!r}): a randomly initialised DeiT; its loop candidates are MEANINGLESS (use it "
                   "for timing only). Set weights to a trained checkpoint or use loop.plugin = 'classical'")
            warnings.warn(msg, UntrainedDeitWarning, stacklevel=2)
            LOG.warning(msg)
        self.descriptor = DeitDescriptor(model, config)
        self.retrieval = LoopRetrieval(config, make_projector(config, ck.pca if ck is not None else None))
        self.verifier = KeyframeVerifier(config) if config.verify else None
        self._pending: list[_Pending] = []
        self._last_id: Optional[int] = None
        self.last_verifications: list[tuple[int, int, float, Verification]] = []  # (i, j, score, result)
        self.forward_batches: list[int] = []  # keyframes per forward pass, in order (diagnostics, tests)
        self._timings: dict[str, float] = {"describe": 0.0, "retrieve": 0.0}

    # --- bookkeeping -----------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.retrieval) + len(self._pending)

    def keyframe_ids(self) -> list[int]:
        return self.retrieval.index.ids + [p.kf_id for p in self._pending]

    @property
    def timings(self) -> dict[str, float]:
        """Seconds per step: describe (preprocess + forward), retrieve, and the verifier's store/features/verify."""
        v = self.verifier.timings if self.verifier is not None else {"store": 0.0, "features": 0.0, "verify": 0.0}
        return {**self._timings, **v}

    def descriptors(self) -> torch.Tensor:
        """float32 ``[N, d]`` unit descriptors of the described keyframes (in ``keyframe_ids`` order)."""
        self.flush()
        return self.retrieval.index.descriptors()

    def similarity_matrix(self) -> torch.Tensor:
        d = self.descriptors()
        return d @ d.T

    # --- LoopDetector --------------------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, frame: Frame) -> None:
        kf_id = int(kf_id)
        if self._last_id is not None and kf_id <= self._last_id:
            raise ValueError(f"deit loop detector: keyframe id {kf_id} after {self._last_id}; keyframes must be "
                             "added in time order")
        image = frame.image
        if image.dim() != 3 or image.shape[0] != 3:
            raise ValueError(f"deit loop detector: keyframe {kf_id}: expected an RGB image [3, H, W], got "
                             f"{tuple(image.shape)}")
        self._last_id = kf_id
        self._pending.append(_Pending(kf_id, image, float(frame.timestamp)))
        if self.verifier is not None:
            self.verifier.add(kf_id, image, frame.intrinsics)
        if len(self._pending) >= self.config.batch_size:
            self.flush()

    def flush(self) -> None:
        """Describe every buffered keyframe (forward passes of ``batch_size``) and add them to the index."""
        if not self._pending:
            return
        t0 = time.perf_counter()
        pending, self._pending = self._pending, []
        feats = self.descriptor.features(torch.stack([p.image for p in pending]))  # [B, D]
        bs = self.config.batch_size
        self.forward_batches += [min(bs, len(pending) - s) for s in range(0, len(pending), bs)]
        self.retrieval.add([p.kf_id for p in pending], feats, [p.timestamp for p in pending])
        self._timings["describe"] += time.perf_counter() - t0

    def query(self, kf_id: int, skip: Optional[Callable[[int], bool]] = None) -> list[LoopCandidate]:
        kf_id = int(kf_id)
        self.flush()
        if kf_id not in self.retrieval:
            raise KeyError(f"deit loop detector: keyframe id {kf_id} is not stored")
        t0 = time.perf_counter()
        matches = self.retrieval.candidates([kf_id])[0]
        self._timings["retrieve"] += time.perf_counter() - t0
        self.last_verifications = []
        out: list[LoopCandidate] = []
        for m in matches:
            if self.verifier is None:
                out.append(LoopCandidate(kf_id, m.match, m.score, verified=None, inliers=0))
                continue
            if skip is not None and skip(m.match):  # the policy would refuse it: spare the verification
                continue
            res = self.verifier.verify(kf_id, m.match)
            if res is None:  # a side without intrinsics: cannot be verified
                continue
            self.last_verifications.append((kf_id, m.match, m.score, res))
            out.append(LoopCandidate(kf_id, m.match, m.score, verified=bool(res.accepted), inliers=res.inliers))
        return out

    def on_keyframe_removed(self, kf_id: int) -> None:
        kf_id = int(kf_id)
        self._pending = [p for p in self._pending if p.kf_id != kf_id]
        if kf_id in self.retrieval:
            self.retrieval.remove(kf_id)
        if self.verifier is not None:
            self.verifier.remove(kf_id)


def make_loop_detector(config: DeitLoopConfig, context: Any = None) -> DeitLoopDetector:
    return DeitLoopDetector(config, getattr(context, "device", None))
