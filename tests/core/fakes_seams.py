"""Three test-only plugins written against the public interfaces alone (issue: core seams for learned plugins).

* ``stateful`` frontend: keeps a "hidden state" per edge keyed by stable keyframe ids (as a RAFT-GRU frontend
  would), and checks on every call that the graph told it about every retired edge and removed keyframe: it never
  holds state for an edge that is not active in the graph (apart from the pair it is observing right now).
* ``retrieval_only`` loop detector: proposes loops on score alone (``verified = None``), as DeiT without geometric
  verification would.
* ``own_categories`` segmenter: labels with its own categories (not the dataset's).

They reuse the exact scene of :mod:`fakes` for targets; nothing here reaches into ``pvslam_core`` internals.
"""
from __future__ import annotations

import torch
from pydantic import Field

from fakes import ExactFrontend, ExactFrontendConfig
from pvslam_core.config_base import PluginConfig
from pvslam_core.interfaces import LoopDetector, Segmenter
from pvslam_core.registry import hookimpl
from pvslam_core.types import Category, LoopCandidate, PanopticSegmentation, Segment


class StatefulFrontend(ExactFrontend):
    """Exact targets plus a per-edge hidden state keyed by stable ids, audited against the graph."""

    instances: list["StatefulFrontend"] = []  # the tests read the built instance after a run

    def __init__(self, cfg, ds):
        super().__init__(cfg, ds)
        self.state: dict[tuple[int, int], torch.Tensor] = {}  # (src id, dst id) -> hidden state
        self.retired: list[tuple[int, int]] = []
        self.removed: list[int] = []
        self.max_state = 0
        self.errors: list[str] = []
        StatefulFrontend.instances.append(self)

    def _audit(self, graph, pending: set) -> None:
        ids = graph.ids.tolist()
        active = {(ids[i], ids[j]) for i, j in zip(graph.ii.tolist(), graph.jj.tolist())}
        stale = set(self.state) - active - pending
        if stale:
            self.errors.append(f"state kept for edges the graph no longer has: {sorted(stale)[:5]}")
        gone = {k for key in self.state for k in key} - set(ids)
        if gone:
            self.errors.append(f"state kept for removed keyframes {sorted(gone)}")

    def observe(self, graph, ii, jj):
        ids = graph.ids
        keys = [(int(ids[i]), int(ids[j])) for i, j in zip(ii.tolist(), jj.tolist())]
        self._audit(graph, pending=set())
        for key in keys:
            h = self.state.get(key)
            self.state[key] = torch.zeros(4) if h is None else h + 1  # "GRU" update
        self.max_state = max(self.max_state, len(self.state))
        return super().observe(graph, ii, jj)

    def on_edges_retired(self, src_ids, dst_ids):
        for key in zip(src_ids.tolist(), dst_ids.tolist()):
            self.retired.append(key)
            self.state.pop(key, None)

    def on_keyframe_removed(self, kf_id):
        super().on_keyframe_removed(kf_id)
        self.removed.append(kf_id)
        for key in [k for k in self.state if kf_id in k]:
            del self.state[key]


class RetrievalOnlyConfig(PluginConfig):
    start: int = Field(6, ge=2, description="keyframe ids from this one on propose a loop with keyframe id 1")


class RetrievalOnlyLoop(LoopDetector):
    """Proposes (id, 1) for every keyframe id >= start, on score alone: ``verified = None``."""

    def __init__(self, cfg: RetrievalOnlyConfig):
        self.cfg = cfg
        self.ids: list[int] = []

    def add_keyframe(self, kf_id, frame):
        self.ids.append(kf_id)

    def on_keyframe_removed(self, kf_id):
        self.ids.remove(kf_id)

    def query(self, kf_id, skip=None):
        if kf_id < self.cfg.start or 1 not in self.ids or (skip is not None and skip(1)):
            return []
        return [LoopCandidate(kf_id, 1, 0.93)]  # verified defaults to None: not checked


CATEGORIES = [Category(7, "lamp post", False, (200, 200, 0)), Category(9, "robot", True, (0, 90, 250))]


class OwnCategoriesSegmenter(Segmenter):
    def categories(self):
        return CATEGORIES

    def segment(self, frame):
        ids = torch.full((frame.height, frame.width), 7000, dtype=torch.int64)
        ids[:, frame.width // 2:] = 9001
        return PanopticSegmentation(ids, [Segment(7000, 7, False), Segment(9001, 9, True)])


class EmptyConfig(PluginConfig):
    pass


@hookimpl
def register_frontends(register):
    register("stateful", lambda c, ctx: StatefulFrontend(c, ctx.ba_downsample), ExactFrontendConfig,
             description="test-only")


@hookimpl
def register_loop_detectors(register):
    register("retrieval_only", lambda c, ctx: RetrievalOnlyLoop(c), RetrievalOnlyConfig, description="test-only")


@hookimpl
def register_segmenters(register):
    register("own_categories", lambda c, ctx: OwnCategoriesSegmenter(), EmptyConfig, description="test-only")
