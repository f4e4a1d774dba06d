"""Poses of every input frame, anchored to keyframes.

Each frame's pose is stored as ``anchor keyframe (stable id)`` plus the relative transform ``T_a^-1 · T_f``, so
the full trajectory follows the keyframes when bundle adjustment or loop closure moves them.  Keyframes are
anchored to themselves with the identity.  For non-keyframes the frontend's correspondences to the anchor (at the
BA resolution) are kept so the relative pose can be re-estimated with motion-only BA once the anchor's depth is
final (:meth:`FramePoses.refill`; the mapper's per-keyframe fill runs on a background thread,
:meth:`FramePoses.refine_many_later`).  When an anchor keyframe is removed, its frames re-anchor to the keyframe
before it (the graph tells, see :meth:`on_keyframe_removed`).  Poses are T_wc ``[t, q_xyzw]``
(:mod:`pvslam_core.types`).

A frame whose anchor was removed has lost its correspondences (they referred to the removed keyframe's pixels), so
no refill re-estimates it.  Held rigidly to the keyframe before, it would not follow the map's scale, which moves
after it is placed (window BAs, the loop pose graph's Sim(3)).  Such a frame is therefore held *between* the
keyframes around it (``FrameEntry.upto``): its pose is the time interpolation of the two
(:func:`~..geometry.lie.se3_interpolate`) composed with the small relative pose it had from that interpolation when
it lost its correspondences, and it follows whatever moves or rescales the two (docs/decisions.md: FRAMES HELD
BETWEEN KEYFRAMES).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Optional

import torch

from ..background import BackgroundWriter
from ..geometry.lie import se3_interpolate, se3_inv, se3_mul

if TYPE_CHECKING:  # pragma: no cover
    from .graph import FrameGraph
    from .spill import SpillStore


@dataclass
class FrameEntry:
    index: int  # input frame index
    timestamp: float
    anchor: int  # stable id of the anchor keyframe
    rel: torch.Tensor  # float64 [7] T_anchor^-1 T_frame
    # handle (FramePoses.spill) of target [2, h, w] (anchor pixels -> this frame) and its weight, for refill
    obs: Optional[int] = None
    is_keyframe: bool = False
    failed: bool = False
    upto: Optional[int] = None  # stable id of the keyframe after it: rel is then from the interpolation of the two


IDENTITY = torch.tensor([0, 0, 0, 0, 0, 0, 1], dtype=torch.float64)


class FramePoses:
    """Every input frame's pose relative to an anchor keyframe of ``graph`` (a GraphListener of it)."""

    def __init__(self, graph: "FrameGraph", robust: Optional[str] = None, robust_scale: float = 1.0,
                 spill: Optional["SpillStore"] = None) -> None:
        from .spill import SpillStore

        self.graph = graph
        self.spill = spill if spill is not None else SpillStore()  # the frames' correspondences
        self._entries: list[FrameEntry] = []
        self.robust, self.robust_scale = robust, robust_scale  # IRLS kernel of the motion-only BA
        # refine_many_later: motion-only BAs on a worker thread, from inputs copied when they were queued. Entries
        # being refined are in _busy; whatever reads or moves them first waits (sync), so every result is the one
        # a call in place would give
        self._worker: Optional[BackgroundWriter] = None
        self._busy: set[int] = set()
        graph.add_listener(self)

    @property
    def entries(self) -> list[FrameEntry]:
        """Every frame's entry, in input order (after the queued refinements have finished)."""
        self.sync()
        return self._entries

    def __len__(self) -> int:
        return len(self._entries)

    def sync(self) -> None:
        """Wait for the queued refinements (re-raises an error of one of them)."""
        if self._busy:
            self._worker.drain()
            self._busy.clear()

    def close(self) -> None:
        """Finish the queued refinements and stop the worker thread (a later refinement starts a new one)."""
        self.sync()
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    def add_keyframe(self, index: int, timestamp: float, kf_id: int) -> None:
        self._entries.append(FrameEntry(index, timestamp, kf_id, IDENTITY.clone(), is_keyframe=True))

    def add_frame(self, index: int, timestamp: float, anchor: int, rel: torch.Tensor,
                  target: Optional[torch.Tensor] = None, weight: Optional[torch.Tensor] = None,
                  failed: bool = False) -> FrameEntry:
        obs = None if target is None else self.spill.put(target, weight)
        e = FrameEntry(index, timestamp, anchor, rel.detach().to("cpu", torch.float64), obs, failed=failed)
        self._entries.append(e)
        return e

    def last_rel(self) -> torch.Tensor:
        if not self._entries:
            return IDENTITY.clone()
        e = self._entries[-1]
        if id(e) in self._busy:
            self.sync()
        if e.upto is None:
            return e.rel.clone()
        return se3_mul(se3_inv(self.graph.poses[self.graph.index_of(e.anchor)].double().cpu()), self.pose_of(e))

    def hold_between(self, e: FrameEntry, anchor: int, upto: Optional[int], pose_wc: torch.Tensor) -> None:
        """Hold entry ``e`` at ``pose_wc`` (float64 [7] T_wc, under the current keyframe poses) between keyframe ids
        ``anchor`` and ``upto`` (None: rigidly to ``anchor``); its correspondences are dropped."""
        self.spill.drop(e.obs)
        e.anchor, e.upto, e.obs = anchor, upto, None
        e.is_keyframe = False
        e.rel = se3_mul(se3_inv(self._bases([e])[0]), pose_wc.double().cpu())

    def rehome(self, kf_id: int, to_id: int, move: Optional[Callable[[torch.Tensor], torch.Tensor]] = None) -> int:
        """Hold keyframe ``kf_id``'s own entry, the frames anchored to it and those held up to it rigidly to keyframe
        ``to_id`` (before ``kf_id`` is removed in favour of ``to_id``), at their poses now, or at ``move`` of them
        (float64 ``[N, 7]`` T_wc -> ``[N, 7]``: where a relocalisation puts them).  Returns how many."""
        self.sync()
        todo = [e for e in self._entries if e.anchor == kf_id or e.upto == kf_id]
        if not todo:
            return 0
        poses = torch.stack([self.pose_of(e) for e in todo])  # [N, 7], all read before any moves
        if move is not None:
            poses = move(poses)
        for e, pose in zip(todo, poses):
            self.hold_between(e, to_id, None, pose)
        return len(todo)

    def bracket(self, anchor: int, upto: int) -> int:
        """Hold the frames rigidly anchored to keyframe id ``anchor`` without correspondences (re-anchored there by a
        removal when no keyframe followed yet) between it and the new keyframe ``upto``, at their poses now.  Returns
        how many."""
        g = self.graph
        ts_a, ts_b = float(g.timestamps[g.index_of(anchor)]), float(g.timestamps[g.index_of(upto)])
        todo = [e for e in self.entries if e.anchor == anchor and e.upto is None and e.obs is None
                and not e.is_keyframe and not e.failed and ts_a < e.timestamp < ts_b]
        for e in todo:
            self.hold_between(e, anchor, upto, self.pose_of(e))
        return len(todo)

    def _bases(self, entries: list[FrameEntry]) -> torch.Tensor:
        """float64 ``[N, 7]`` T_wc that each entry's ``rel`` is relative to: its anchor keyframe, or for a frame held
        up to ``upto`` the interpolation of the two at its timestamp."""
        g = self.graph
        anchors = g.indices_of(torch.tensor([e.anchor for e in entries], dtype=torch.int64)).cpu()
        if bool((anchors < 0).any()):
            raise RuntimeError("a frame is anchored to a keyframe that is no longer in the graph")
        kf_poses = g.poses.double().cpu()
        base = kf_poses[anchors]  # [N, 7]
        held = torch.tensor([n for n, e in enumerate(entries) if e.upto is not None], dtype=torch.int64)
        if held.numel():  # frames held between two keyframes: [H] rows
            upto = g.indices_of(torch.tensor([entries[n].upto for n in held.tolist()], dtype=torch.int64)).cpu()
            if bool((upto < 0).any()):
                raise RuntimeError("a frame is held up to a keyframe that is no longer in the graph")
            kf_ts = g.timestamps.double().cpu()
            ts = torch.tensor([entries[n].timestamp for n in held.tolist()], dtype=torch.float64)
            ts_a, ts_b = kf_ts[anchors[held]], kf_ts[upto]
            alpha = torch.where(ts_b > ts_a, (ts - ts_a) / (ts_b - ts_a).clamp(min=1e-12), torch.zeros_like(ts_a))
            base[held] = se3_interpolate(base[held], kf_poses[upto], alpha)
        return base

    # ------------------------------------------------------------------------------------ GraphListener --
    def on_keyframe_removed(self, kf_id: int) -> None:
        """Frames anchored to ``kf_id`` (and its own entry) are held, at their poses now, between the keyframes
        before and after it (rigidly to the one before when it is the newest); frames held up to it, up to the one
        after it."""
        self.sync()  # the refinements of its frames finish before they move
        g = self.graph
        k = g.index_of(kf_id)
        if k == 0:
            raise ValueError("the first keyframe cannot be removed (it anchors the map)")
        prev_id = g.id_of(k - 1)
        next_id = g.id_of(k + 1) if k + 1 < g.n else None
        for e in self.entries:
            if e.anchor == kf_id:  # its correspondences referred to the removed keyframe's pixels
                self.hold_between(e, prev_id, next_id, self.pose_of(e))
            elif e.upto == kf_id:
                self.hold_between(e, e.anchor, next_id, self.pose_of(e))

    def on_edges_retired(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        pass

    # ----------------------------------------------------------------------------------------- queries --
    def pending(self, anchor: int) -> list[FrameEntry]:
        """Non-keyframes anchored to keyframe id ``anchor`` (anchors are never changed by a queued refinement)."""
        return [e for e in self._entries if e.anchor == anchor and not e.is_keyframe]

    def poses(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(timestamps float64 [T], poses float64 [T, 7])`` for every frame so far, vectorised."""
        if not self.entries:
            return torch.zeros(0, dtype=torch.float64), torch.zeros(0, 7, dtype=torch.float64)
        ts = torch.tensor([e.timestamp for e in self.entries], dtype=torch.float64)
        rel = torch.stack([e.rel for e in self.entries])  # [T, 7]
        return ts, se3_mul(self._bases(self.entries), rel)

    def pose_of(self, e: FrameEntry) -> torch.Tensor:
        """float64 [7] T_wc of one entry under the current keyframe poses."""
        if id(e) in self._busy:
            self.sync()
        return se3_mul(self._bases([e])[0], e.rel)

    # ---------------------------------------------------------------------------------- motion-only BA --
    def motion_only(self, init_wc: torch.Tensor, kf_pose: torch.Tensor, kf_disp: torch.Tensor, intr: torch.Tensor,
                    target: torch.Tensor, weight: torch.Tensor, iters: int = 4) -> Optional[torch.Tensor]:
        """Pose ``T_wc`` (float64 [7], CPU) of a frame from flow targets of a keyframe (pose ``kf_pose``, depth
        ``kf_disp``) by motion-only BA with this object's robust kernel, from ``init_wc``; None if not finite."""
        from ..geometry.ba import motion_only_ba

        t_a = kf_pose.double()
        pose, _cost = motion_only_ba(init_wc.to(t_a.device), t_a, kf_disp, intr, target, weight, iters=iters,
                                     robust=self.robust, robust_scale=self.robust_scale)
        return pose.double().cpu() if bool(torch.isfinite(pose).all()) else None

    def place_pending(self, anchor: int) -> bool:
        """Queue one batched motion-only BA (:meth:`refine_many_later`) for the non-keyframes anchored at keyframe id
        ``anchor`` that have correspondences, once its depth is refined: each starts from the time interpolation
        between the anchor and the keyframe after it.  Returns whether there were any."""
        pend = [e for e in self.pending(anchor) if e.obs is not None]
        if not pend:
            return False
        g = self.graph
        a = g.index_of(anchor)
        t_a = g.poses[a].double().cpu()
        nxt = g.poses[a + 1].double().cpu() if a + 1 < g.n else t_a
        ts_a = float(g.timestamps[a])
        ts_b = float(g.timestamps[a + 1]) if a + 1 < g.n else ts_a
        alpha = torch.tensor([0.0 if ts_b <= ts_a else (e.timestamp - ts_a) / (ts_b - ts_a) for e in pend],
                             dtype=torch.float64)
        inits = se3_interpolate(t_a.expand(len(pend), 7), nxt.expand(len(pend), 7), alpha)
        self.refine_many_later(pend, inits)
        return True

    def refine(self, e: FrameEntry, init_wc: torch.Tensor, iters: int = 4) -> bool:
        """Motion-only BA of entry ``e`` against its anchor keyframe, starting from ``init_wc``; stores the new
        relative pose. False (unchanged) when the result is not finite."""
        return self.refine_many([e], init_wc.reshape(1, 7), iters) == 1

    def refine_many(self, entries: list[FrameEntry], inits_wc: torch.Tensor, iters: int = 4) -> int:
        """:meth:`refine` for several entries (one batched motion-only BA per anchor keyframe, from ``inits_wc
        [len(entries), 7]``). Returns how many were updated."""
        self.sync()
        return self._run(entries, self._plan(entries, inits_wc), iters)

    def refine_many_later(self, entries: list[FrameEntry], inits_wc: torch.Tensor, iters: int = 4) -> None:
        """:meth:`refine_many` on a worker thread: its inputs (anchor poses and depths, targets) are copied now, the
        entries' relative poses are written when it has run; every reader of those entries waits for it.  Why: the
        mapper refines a keyframe's frames once its depth is final, and nothing needs them before the output (or a
        keyframe removal), so the ~2.5 ms a frame of motion-only BA need not hold up the next frames' tracking."""
        if not entries:
            return
        plan = self._plan(entries, inits_wc, copy=True)
        if self._worker is None:
            self._worker = BackgroundWriter(depth=8, name="pvslam-poses")
        self._busy.update(id(e) for e in entries)
        self._worker.submit(self._run, list(entries), plan, iters)

    def _plan(self, entries: list[FrameEntry], inits_wc: torch.Tensor, copy: bool = False) -> list[tuple]:
        """Per anchor keyframe: ``(rows, anchor pose, anchor depth, intrinsics, inits, targets, weights)``."""
        g = self.graph
        by_anchor: dict[int, list[int]] = {}
        for n, e in enumerate(entries):
            by_anchor.setdefault(e.anchor, []).append(n)
        plan = []
        for anchor, rows in by_anchor.items():
            a = g.index_of(anchor)
            t_a = g.poses[a].double()  # views of the graph's storage, which the BA updates in place: copied
            t_a, disp, intr = (t_a.clone(), g.disps[a].clone(), g.intrinsics.clone()) if copy else \
                (t_a, g.disps[a], g.intrinsics)
            obs = [self.spill.get(entries[n].obs) for n in rows]
            target = torch.stack([o[0] for o in obs])
            weight = torch.stack([o[1] for o in obs])
            del obs
            plan.append((rows, t_a, disp, intr, inits_wc[rows].to(t_a.device, torch.float64), target, weight))
        return plan

    def _run(self, entries: list[FrameEntry], plan: list[tuple], iters: int) -> int:
        from ..geometry.ba import motion_only_ba

        done = 0
        for rows, t_a, disp, intr, init, target, weight in plan:
            poses, costs = motion_only_ba(init, t_a, disp, intr, target, weight, iters=iters,
                                          robust=self.robust, robust_scale=self.robust_scale)
            ok = torch.isfinite(poses).all(-1).tolist()  # a failed solve returns its (finite) start pose
            inv_a = se3_inv(t_a.cpu())
            rel = se3_mul(inv_a.expand(len(rows), 7), poses.double().cpu())
            for m, n in enumerate(rows):
                if ok[m]:
                    entries[n].rel, entries[n].upto = rel[m], None  # solved against the anchor alone
                    done += 1
        return done

    def refill(self, iters: int = 4) -> int:
        """Re-estimate the relative pose of every non-keyframe that still has correspondences. Returns the count."""
        todo = [e for e in self.entries if not e.is_keyframe and e.obs is not None]
        if not todo:
            return 0
        _, poses = self.poses()
        index = {id(e): n for n, e in enumerate(self.entries)}
        return self.refine_many(todo, poses[[index[id(e)] for e in todo]], iters)
