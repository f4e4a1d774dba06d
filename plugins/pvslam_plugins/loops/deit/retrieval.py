"""Model-independent loop retrieval over global descriptors keyed by stable keyframe ids.

* :class:`KeyframeIndex` stores the *raw* descriptors (before PCA) with their keyframe id (an int chosen by the
  caller that never changes; removal is by id) and timestamp, in insertion order.  The unit descriptors used for
  the cosine similarity (eq. 8) are ``L2(projector.transform(raw))``, cached and recomputed whenever the
  projector's ``version`` changes (an online PCA refit), so every pair compared went through the same transform.
* :func:`KeyframeIndex.candidates`: for each query keyframe, older keyframes with similarity >= threshold,
  outside the temporal exclusion window, best ``max_candidates`` first (vectorised over a batch of queries).
  "Older" and "more than ``exclude_recent`` keyframes older" use the position in insertion order among the
  keyframes still stored (as the frame graph's shifting indices do); ``min_time_gap`` uses the timestamps.
* :class:`LoopRetrieval` ties the index to a projector that may learn online (an :class:`~.pca.OnlinePCA`).

Acceptance rules beyond retrieval (consecutive hits, suppression near accepted loops, orientation) are the
mapper's loop policy (:mod:`pvslam_core.slam.loops`), not a detector's.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Protocol, Sequence, Union

import torch

from .config import RetrievalConfig

IdsLike = Union[int, Sequence[int], torch.Tensor]


class Projector(Protocol):
    version: int

    def transform(self, x: torch.Tensor) -> torch.Tensor: ...


@dataclass(frozen=True)
class Match:
    query: int  # keyframe id of the newer keyframe
    match: int  # keyframe id of the older keyframe it looks like
    score: float  # cosine similarity in [-1, 1]


def l2_normalize(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True).clamp_min(eps)


def _as_ids(ids: IdsLike) -> list[int]:
    if isinstance(ids, torch.Tensor):
        return [int(i) for i in ids.reshape(-1).tolist()]
    if isinstance(ids, int):
        return [ids]
    return [int(i) for i in ids]


class KeyframeIndex:
    """Raw descriptors ``[N, D]`` + ids + timestamps, in insertion order; unit descriptors on demand."""

    def __init__(self, projector: Optional[Projector] = None) -> None:
        self.projector = projector
        self._raw = torch.zeros(0, 0)  # [capacity, D] float32; rows [0, n) valid
        self._times = torch.zeros(0, dtype=torch.float64)  # [capacity]
        self._ids: list[int] = []
        self._row: dict[int, int] = {}  # id -> row (= position)
        self._desc: Optional[torch.Tensor] = None  # [n_desc, d] unit descriptors of rows [0, n_desc)
        self._desc_version: object = None

    # --- bookkeeping -------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._ids)

    def __contains__(self, kf_id: int) -> bool:
        return int(kf_id) in self._row

    @property
    def ids(self) -> list[int]:
        return list(self._ids)

    def position(self, kf_id: int) -> int:
        """Position of a keyframe in insertion order among the stored ones (0 = oldest)."""
        try:
            return self._row[int(kf_id)]
        except KeyError:
            raise KeyError(f"keyframe id {kf_id} is not in the index ({len(self)} stored)") from None

    @property
    def raw(self) -> torch.Tensor:
        """float32 ``[N, D]`` raw descriptors (a view)."""
        return self._raw[: len(self)]

    @property
    def timestamps(self) -> torch.Tensor:
        return self._times[: len(self)]

    def add(self, ids: IdsLike, features: torch.Tensor, timestamps: Union[float, Sequence[float], torch.Tensor]
            ) -> None:
        """Append keyframes ``ids`` (new, in time order) with raw descriptors ``[B, D]`` and timestamps ``[B]``."""
        id_list = _as_ids(ids)
        f = features.detach().float().cpu()
        f = f[None] if f.dim() == 1 else f  # [D] for a single id -> [1, D]
        if f.dim() != 2:
            raise ValueError(f"add: descriptors must be [B, D], got {tuple(features.shape)}")
        t = torch.as_tensor(timestamps, dtype=torch.float64).reshape(-1)
        if f.shape[0] != len(id_list) or t.shape[0] != len(id_list):
            raise ValueError(f"add: {len(id_list)} ids, {f.shape[0]} descriptors, {t.shape[0]} timestamps")
        dup = [i for i in id_list if i in self._row] + [i for k, i in enumerate(id_list) if i in id_list[:k]]
        if dup:
            raise ValueError(f"keyframe ids already stored (ids must be unique): {dup[:5]}")
        n, B = len(self), len(id_list)
        if self._raw.shape[1] != f.shape[1]:
            if n:
                raise ValueError(f"descriptor size {f.shape[1]} differs from the stored {self._raw.shape[1]}")
            self._raw = torch.zeros(max(16, B), f.shape[1])
            self._times = torch.zeros(max(16, B), dtype=torch.float64)
        if n + B > self._raw.shape[0]:
            cap = max(2 * self._raw.shape[0], n + B)
            self._raw = torch.cat([self._raw[:n], torch.zeros(cap - n, f.shape[1])])
            self._times = torch.cat([self._times[:n], torch.zeros(cap - n, dtype=torch.float64)])
        self._raw[n : n + B] = f
        self._times[n : n + B] = t
        for k, i in enumerate(id_list):
            self._row[i] = n + k
        self._ids.extend(id_list)

    def remove(self, kf_id: int) -> None:
        r = self.position(kf_id)
        n = len(self)
        self._raw[r : n - 1] = self._raw[r + 1 : n].clone()
        self._times[r : n - 1] = self._times[r + 1 : n].clone()
        del self._ids[r]
        self._row = {i: k for k, i in enumerate(self._ids)}
        if self._desc is not None and self._desc.shape[0] > r:
            self._desc = torch.cat([self._desc[:r], self._desc[r + 1 :]])

    # --- descriptors ---------------------------------------------------------------------------------------------
    def describe(self, features: torch.Tensor) -> torch.Tensor:
        """Unit descriptors ``[B, d]`` of raw descriptors ``[B, D]`` with the current projector."""
        x = features.float()
        if self.projector is not None:
            x = self.projector.transform(x)
        return l2_normalize(x)

    def descriptors(self) -> torch.Tensor:
        """float32 ``[N, d]`` unit descriptors of every stored keyframe (cached; see the module docstring)."""
        version = (id(self.projector), getattr(self.projector, "version", 0))
        n = len(self)
        if self._desc is None or self._desc_version != version:
            self._desc = self.describe(self.raw) if n else torch.zeros(0, 0)
            self._desc_version = version
        elif self._desc.shape[0] < n:
            self._desc = torch.cat([self._desc, self.describe(self._raw[self._desc.shape[0] : n])]) \
                if self._desc.shape[0] else self.describe(self.raw)
        return self._desc

    def similarity_matrix(self) -> torch.Tensor:
        """``[N, N]`` cosine similarities between all stored keyframes (for evaluation / calibration)."""
        d = self.descriptors()
        return d @ d.T

    # --- retrieval ----------------------------------------------------------------------------------------------
    def candidates(self, query_ids: IdsLike, threshold: float, exclude_recent: int = 0, min_time_gap: float = 0.0,
                   max_candidates: int = 1) -> list[list[Match]]:
        """For each stored query keyframe: older keyframes at position ``<= pos(query) - 1 - exclude_recent``,
        at least ``min_time_gap`` seconds older, with similarity ``>= threshold``; best first, at most
        ``max_candidates``."""
        q_ids = _as_ids(query_ids)
        if not q_ids:
            return []
        desc = self.descriptors()  # [N, d]
        rows = torch.tensor([self.position(i) for i in q_ids])  # [B]
        sims = desc[rows] @ desc.T  # [B, N]
        pos = torch.arange(len(self))
        ok = pos[None, :] <= rows[:, None] - 1 - int(exclude_recent)
        ok &= (self.timestamps[rows][:, None] - self.timestamps[None, :]) >= float(min_time_gap)
        ok &= sims >= float(threshold)
        masked = torch.where(ok, sims, torch.full_like(sims, float("-inf")))
        k = min(int(max_candidates), len(self))
        top, idx = masked.topk(k, dim=1) if k else (masked[:, :0], masked[:, :0].long())  # [B, k]
        out: list[list[Match]] = []
        for b, q in enumerate(q_ids):
            out.append([Match(q, self._ids[int(j)], float(s)) for s, j in zip(top[b].tolist(), idx[b].tolist())
                        if s != float("-inf")])
        return out


class LoopRetrieval:
    """Index + (online) projector + retrieval settings.

    ``add(ids, raw [B, D], timestamps [B])`` updates an online projector's statistics (objects with an ``update``
    method, e.g. :class:`~.pca.OnlinePCA`) with the new descriptors and stores them; ``candidates(ids)`` returns
    each stored query keyframe's matches, best first.  Adding a batch and then querying its keyframes gives the
    same matches as adding and querying one keyframe at a time, except that an online PCA sees the whole batch
    before any of its queries.
    """

    def __init__(self, config: Optional[RetrievalConfig] = None, projector: Optional[Projector] = None) -> None:
        self.config = config or RetrievalConfig()
        self.index = KeyframeIndex(projector)

    @property
    def projector(self) -> Optional[Projector]:
        return self.index.projector

    def __len__(self) -> int:
        return len(self.index)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self.index

    def candidates(self, query_ids: IdsLike) -> list[list[Match]]:
        """Retrieval only (threshold, exclusion, max_candidates); changes nothing."""
        c = self.config
        return self.index.candidates(query_ids, c.threshold, c.exclude_recent, c.min_time_gap, c.max_candidates)

    def add(self, ids: IdsLike, features: torch.Tensor, timestamps: Union[float, Sequence[float], torch.Tensor]
            ) -> None:
        self.index.add(ids, features, timestamps)  # validates first: a rejected batch leaves no trace
        update = getattr(self.projector, "update", None)
        if update is not None:
            update(features.reshape(-1, features.shape[-1]))

    def remove(self, kf_id: int) -> None:
        self.index.remove(kf_id)
