"""The frame graph: keyframe store (stable id, pose, inverse depth at the BA resolution) plus directed edges
``i -> j`` with a lifecycle.

Keyframes.  Each keyframe has a graph *index* (``0..n-1``, what the BA's edge lists hold; it shifts down when an
older keyframe is removed) and a stable *id* (``ids[k]``, assigned once, never reused).  Ids grow with the index,
so ``indices_of`` is a binary search.  Storage grows geometrically (amortised O(1) ``add_keyframe``); the public
attributes are views of the first ``n`` rows.  Poses are ``T_wc`` (camera-to-world, float64), see
:mod:`pvslam_core.types`.

Edges.  ``ii``/``jj``/``edge_kind``/``edge_age`` are the *active* edges, the ones the window and loop BAs use and
the frontend keeps per-edge state for.  ``edge_age`` counts the optimisation rounds an edge took part in
(:meth:`age_edges`).  :meth:`retire_edges` moves edges out of the active set (DROID-SLAM's ``rm_factors(...,
store=True)``): the last observation recorded for each (:meth:`record_observations`) is kept, as a flow offset
and a weight in float16 (about 10 KB per edge at 40x30), for the final global BA; listeners hear
``on_edges_retired`` so per-edge state can go.  :meth:`all_edges` lists active and retired edges.

Listeners (:class:`~pvslam_core.interfaces.GraphListener`) hear ``on_keyframe_removed(id)`` before a keyframe's
data is dropped and ``on_edges_retired(src_ids, dst_ids)`` after edges are retired.  This is the only place that
shifts indices.
"""
from __future__ import annotations

from typing import Any, Iterable, Optional

import torch

from ..geometry.projective import frame_distance as _frame_distance
from ..types import EdgeObservations
from .spill import SpillStore

EDGE_ODOMETRY = 0  # odometry / neighbourhood edge
EDGE_PROXIMITY = 1
EDGE_LOOP = 2
EDGE_KIND_NAMES = {EDGE_ODOMETRY: "odometry", EDGE_PROXIMITY: "proximity", EDGE_LOOP: "loop"}


class FrameGraph:
    def __init__(self, ba_height: int, ba_width: int, intrinsics: torch.Tensor, device="cpu", capacity: int = 64,
                 spill: Optional[SpillStore] = None):
        self.device = torch.device(device)
        self.ba_shape = (int(ba_height), int(ba_width))
        self.intrinsics = torch.as_tensor(intrinsics, dtype=torch.float32).to(self.device).reshape(4).clone()
        capacity = max(1, int(capacity))
        self.n = 0
        self.next_id = 0
        h, w = self.ba_shape
        self._poses = torch.zeros(capacity, 7, dtype=torch.float64, device=self.device)
        self._disps = torch.zeros(capacity, h, w, dtype=torch.float32, device=self.device)
        self._frame_index = torch.zeros(capacity, dtype=torch.int64, device=self.device)
        self._timestamps = torch.zeros(capacity, dtype=torch.float64, device=self.device)
        self._ids = torch.zeros(capacity, dtype=torch.int64, device=self.device)
        self._ids_cpu: list[int] = []  # the same ids, for Python-side lookups without device syncs
        self.ii = torch.zeros(0, dtype=torch.int64, device=self.device)
        self.jj = torch.zeros(0, dtype=torch.int64, device=self.device)
        self.edge_age = torch.zeros(0, dtype=torch.int64, device=self.device)
        self.edge_kind = torch.zeros(0, dtype=torch.int8, device=self.device)
        self.edge_born = torch.zeros(0, dtype=torch.int64, device=self.device)  # next_id when the edge was added
        self._last_obs: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]] = {}  # (src id, dst id) -> target, weight
        # (src id, dst id) -> (handle of [offset f16, weight f16] in the spill store, kind)
        self._retired: dict[tuple[int, int], tuple[int, int]] = {}
        self.spill = spill if spill is not None else SpillStore()
        self.retired_total = 0  # edges ever retired (statistics)
        self.listeners: list[Any] = []

    # ------------------------------------------------------------------------------------------- views
    @property
    def capacity(self) -> int:
        return int(self._poses.shape[0])

    @property
    def poses(self) -> torch.Tensor:
        return self._poses[: self.n]

    @property
    def disps(self) -> torch.Tensor:
        return self._disps[: self.n]

    @property
    def frame_index(self) -> torch.Tensor:
        return self._frame_index[: self.n]

    @property
    def timestamps(self) -> torch.Tensor:
        return self._timestamps[: self.n]

    @property
    def ids(self) -> torch.Tensor:
        """int64 ``[n]`` stable keyframe ids (ascending)."""
        return self._ids[: self.n]

    @property
    def num_edges(self) -> int:
        """Active edges."""
        return int(self.ii.shape[0])

    @property
    def num_retired(self) -> int:
        return len(self._retired)

    def __len__(self) -> int:
        return self.n

    def __repr__(self) -> str:
        return (f"FrameGraph(n={self.n}, edges={self.num_edges} active + {self.num_retired} retired, "
                f"ba_shape={self.ba_shape}, device={self.device})")

    # ------------------------------------------------------------------------------------------- ids
    def id_of(self, k: int) -> int:
        """Stable id of the keyframe at graph index ``k``."""
        if not -self.n <= int(k) < self.n:
            raise IndexError(f"keyframe index {k} out of range (n={self.n})")
        return self._ids_cpu[int(k)]

    def index_of(self, kf_id: int) -> int:
        """Graph index of keyframe ``kf_id``; KeyError when it is not (or no longer) in the graph."""
        import bisect

        k = bisect.bisect_left(self._ids_cpu, int(kf_id))
        if k >= self.n or self._ids_cpu[k] != int(kf_id):
            raise KeyError(f"keyframe id {kf_id} is not in the graph")
        return k

    def has_id(self, kf_id: int) -> bool:
        try:
            self.index_of(kf_id)
            return True
        except KeyError:
            return False

    def indices_of(self, kf_ids) -> torch.Tensor:
        """int64 graph indices of ``kf_ids`` (any shape), ``-1`` where an id is not in the graph."""
        q = torch.as_tensor(kf_ids, dtype=torch.int64, device=self.device)
        if self.n == 0:
            return torch.full_like(q, -1)
        pos = torch.searchsorted(self.ids, q.reshape(-1)).clamp(max=self.n - 1)
        found = self.ids[pos] == q.reshape(-1)
        return torch.where(found, pos, torch.full_like(pos, -1)).reshape(q.shape)

    def add_listener(self, listener: Any) -> None:
        """Register a :class:`~pvslam_core.interfaces.GraphListener` (each object once)."""
        if listener is not None and all(listener is not l for l in self.listeners):
            self.listeners.append(listener)

    # ------------------------------------------------------------------------------------------- keyframes
    def _grow(self, need: int) -> None:
        if need <= self.capacity:
            return
        cap = self.capacity
        while cap < need:
            cap *= 2

        def grown(t: torch.Tensor) -> torch.Tensor:
            out = torch.zeros((cap,) + tuple(t.shape[1:]), dtype=t.dtype, device=t.device)
            out[: self.n] = t[: self.n]
            return out

        self._poses = grown(self._poses)
        self._disps = grown(self._disps)
        self._frame_index = grown(self._frame_index)
        self._timestamps = grown(self._timestamps)
        self._ids = grown(self._ids)

    def add_keyframe(self, frame_index: int, timestamp: float, pose_wc: torch.Tensor, disp: torch.Tensor) -> int:
        """Append a keyframe; returns its index (``n - 1`` afterwards).  Its stable id is ``ids[-1]``."""
        h, w = self.ba_shape
        disp = torch.as_tensor(disp)
        if disp.dim() == 0:
            disp = disp.expand(h, w)
        if tuple(disp.shape[-2:]) != (h, w):
            raise ValueError(f"disp must be [{h}, {w}] (BA resolution), got {tuple(disp.shape)}")
        pose_wc = torch.as_tensor(pose_wc).reshape(7)
        self._grow(self.n + 1)
        k = self.n
        self._poses[k] = pose_wc.to(self.device, torch.float64)
        self._disps[k] = disp.reshape(h, w).to(self.device, torch.float32)
        self._frame_index[k] = int(frame_index)
        self._timestamps[k] = float(timestamp)
        self._ids[k] = self.next_id
        self._ids_cpu.append(self.next_id)
        self.next_id += 1
        self.n += 1
        return k

    def remove_keyframe(self, k: int) -> None:
        """Remove keyframe ``k`` and every edge touching it (active and retired); later keyframes (and edge ends)
        shift down by one.  Listeners hear ``on_keyframe_removed`` first, while the keyframe is still readable."""
        k = int(k)
        if not 0 <= k < self.n:
            raise IndexError(f"keyframe {k} out of range (n={self.n})")
        kf_id = self._ids_cpu[k]
        for listener in list(self.listeners):
            listener.on_keyframe_removed(kf_id)
        for buf in (self._poses, self._disps, self._frame_index, self._timestamps, self._ids):
            buf[k : self.n - 1] = buf[k + 1 : self.n].clone()
        del self._ids_cpu[k]
        self.n -= 1
        keep = (self.ii != k) & (self.jj != k)
        self._keep_edges(keep)
        self.ii = self.ii - (self.ii > k).long()
        self.jj = self.jj - (self.jj > k).long()
        for store in (self._last_obs, self._retired):
            for key in [key for key in store if kf_id in key]:
                if store is self._retired:
                    self.spill.drop(store[key][0])
                del store[key]

    # ------------------------------------------------------------------------------------------- edges
    def _keep_edges(self, keep: torch.Tensor) -> None:
        """Drop active edges where ``keep`` is False (callers clean ``_last_obs`` themselves)."""
        self.ii, self.jj = self.ii[keep], self.jj[keep]
        self.edge_age, self.edge_kind = self.edge_age[keep], self.edge_kind[keep]
        self.edge_born = self.edge_born[keep]

    def _keys(self, ii: torch.Tensor, jj: torch.Tensor) -> torch.Tensor:
        m = max(self.n, 1)
        return ii * m + jj

    def has_edges(self, ii, jj) -> torch.Tensor:
        """bool ``[len(ii)]``: whether each ``ii -> jj`` is an active edge."""
        ii = torch.as_tensor(ii, dtype=torch.int64, device=self.device).reshape(-1)
        jj = torch.as_tensor(jj, dtype=torch.int64, device=self.device).reshape(-1)
        if self.num_edges == 0 or len(ii) == 0:
            return torch.zeros(len(ii), dtype=torch.bool, device=self.device)
        return torch.isin(self._keys(ii, jj), self._keys(self.ii, self.jj))

    def add_edges(self, ii, jj, kind: int = EDGE_ODOMETRY) -> torch.Tensor:
        """Add active edges ``ii -> jj``; self-edges, out-of-range ends and duplicates (with active edges or within
        the call) are skipped; a retired edge that is added again becomes active (its stored observation goes).
        Returns the bool mask ``[len(ii)]`` of edges actually added (new edges have age 0)."""
        ii = torch.as_tensor(ii, dtype=torch.int64, device=self.device).reshape(-1)
        jj = torch.as_tensor(jj, dtype=torch.int64, device=self.device).reshape(-1)
        if ii.shape != jj.shape:
            raise ValueError(f"ii and jj differ in length: {tuple(ii.shape)} vs {tuple(jj.shape)}")
        ok = (ii != jj) & (ii >= 0) & (jj >= 0) & (ii < self.n) & (jj < self.n)
        ok &= ~self.has_edges(ii, jj)
        if ok.any():
            # duplicates inside this call: keep the first occurrence
            key = self._keys(ii, jj)
            idx = torch.nonzero(ok).squeeze(1)
            _, inv = torch.unique(key[idx], return_inverse=True)
            first = torch.full((int(inv.max()) + 1,), len(idx), dtype=torch.int64, device=self.device)
            first.scatter_reduce_(0, inv, torch.arange(len(idx), device=self.device), reduce="amin")
            ok = torch.zeros_like(ok)
            ok[idx[first]] = True
        sel = torch.nonzero(ok).squeeze(1)
        if len(sel):
            if self._retired:
                for i, j in zip(ii[sel].tolist(), jj[sel].tolist()):
                    self.spill.drop(self._retired.pop((self._ids_cpu[i], self._ids_cpu[j]), (None,))[0])
            self.ii = torch.cat([self.ii, ii[sel]])
            self.jj = torch.cat([self.jj, jj[sel]])
            self.edge_age = torch.cat([self.edge_age, torch.zeros(len(sel), dtype=torch.int64, device=self.device)])
            self.edge_kind = torch.cat(
                [self.edge_kind, torch.full((len(sel),), int(kind), dtype=torch.int8, device=self.device)]
            )
            self.edge_born = torch.cat(
                [self.edge_born, torch.full((len(sel),), self.next_id, dtype=torch.int64, device=self.device)]
            )
        return ok

    def edge_mask(self, ii, jj) -> torch.Tensor:
        """bool ``[num_edges]``: the active edges that are among ``ii -> jj``."""
        ii = torch.as_tensor(ii, dtype=torch.int64, device=self.device).reshape(-1)
        jj = torch.as_tensor(jj, dtype=torch.int64, device=self.device).reshape(-1)
        if self.num_edges == 0 or len(ii) == 0:
            return torch.zeros(self.num_edges, dtype=torch.bool, device=self.device)
        return torch.isin(self._keys(self.ii, self.jj), self._keys(ii, jj))

    def age_edges(self, ii, jj, by: int = 1) -> None:
        """One more optimisation round for the active edges among ``ii -> jj``."""
        self.edge_age = self.edge_age + int(by) * self.edge_mask(ii, jj).long()

    def record_observations(self, obs: EdgeObservations) -> None:
        """Remember the latest observation of each active edge in ``obs`` (kept if the edge is retired)."""
        if obs.ii.numel() == 0:
            return
        active = self.has_edges(obs.ii, obs.jj).tolist()
        ids = self._ids_cpu
        for e, (i, j) in enumerate(zip(obs.ii.tolist(), obs.jj.tolist())):
            if active[e]:
                self._last_obs[(ids[i], ids[j])] = (obs.target[e], obs.weight[e])

    def retire_edges(self, mask: torch.Tensor) -> int:
        """Move the active edges where ``mask`` is True to the retired store (their last recorded observation is
        kept for :meth:`retired_observations`; an edge never observed is simply dropped).  Listeners hear
        ``on_edges_retired``.  Returns the number retired."""
        mask = torch.as_tensor(mask, dtype=torch.bool, device=self.device).reshape(-1)
        if mask.shape[0] != self.num_edges:
            raise ValueError(f"mask has {mask.shape[0]} entries for {self.num_edges} edges")
        sel = torch.nonzero(mask).squeeze(1)
        if len(sel) == 0:
            return 0
        h, w = self.ba_shape
        grid = _grid(h, w, self.device)
        src = self.ids[self.ii[sel]]
        dst = self.ids[self.jj[sel]]
        for s, d, kind in zip(src.tolist(), dst.tolist(), self.edge_kind[sel].tolist()):
            last = self._last_obs.pop((s, d), None)
            if last is not None:
                target, weight = last
                offset = (target.to(self.device, torch.float32) - grid).to(torch.float16)
                self._retired[(s, d)] = (self.spill.put(offset, weight.to(self.device, torch.float16)), int(kind))
        self.retired_total += len(sel)
        self._keep_edges(~mask)
        for listener in list(self.listeners):
            listener.on_edges_retired(src, dst)
        return int(len(sel))

    def retired_edges(self, lo: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """``(ii, jj)`` graph indices of the retired edges that have a stored observation, those whose both ends are
        keyframes ``>= lo`` (indices follow the ids' order; 0: all of them)."""
        z = torch.zeros(0, dtype=torch.int64, device=self.device)
        lo = max(0, int(lo))
        if not self._retired or lo >= self.n:
            return z, z.clone()
        id_lo = self._ids_cpu[lo]
        keys = [key for key in self._retired if key[0] >= id_lo and key[1] >= id_lo]
        if not keys:
            return z, z.clone()
        idx = self.indices_of(torch.tensor(keys, dtype=torch.int64, device=self.device))  # [R, 2] ids -> indices
        return idx[:, 0], idx[:, 1]

    def is_retired(self, ii, jj) -> torch.Tensor:
        """bool ``[len(ii)]``: whether each ``ii -> jj`` has a stored retired observation."""
        ii = torch.as_tensor(ii, dtype=torch.int64).reshape(-1).tolist()
        jj = torch.as_tensor(jj, dtype=torch.int64).reshape(-1).tolist()
        ids = self._ids_cpu
        return torch.tensor([(ids[i], ids[j]) in self._retired for i, j in zip(ii, jj)], dtype=torch.bool)

    def retired_observations(self, ii, jj) -> EdgeObservations:
        """The stored observations of retired edges ``ii -> jj`` (graph indices; each must be retired)."""
        ii = torch.as_tensor(ii, dtype=torch.int64, device=self.device).reshape(-1)
        jj = torch.as_tensor(jj, dtype=torch.int64, device=self.device).reshape(-1)
        h, w = self.ba_shape
        target = torch.empty(len(ii), 2, h, w, dtype=torch.float32, device=self.device)
        weight = torch.empty_like(target)
        self.retired_observations_into(ii, jj, target, weight, torch.arange(len(ii)))
        return EdgeObservations(ii, jj, target, weight)

    def retired_observations_into(self, ii, jj, target: torch.Tensor, weight: torch.Tensor, rows) -> None:
        """Write the stored observation of retired edge ``ii[n] -> jj[n]`` into row ``rows[n]`` of ``target`` and
        ``weight`` (``[E, 2, h, w]``, float32 or wider) one edge at a time: no stack of them all is made."""
        ids = self._ids_cpu
        grid = _grid(*self.ba_shape, self.device)
        for i, j, r in zip(torch.as_tensor(ii).tolist(), torch.as_tensor(jj).tolist(), torch.as_tensor(rows).tolist()):
            entry = self._retired.get((ids[i], ids[j]))
            if entry is None:
                raise KeyError(f"edge {i} -> {j} (ids {ids[i]} -> {ids[j]}) has no retired observation")
            offset, wt = self.spill.get(entry[0])
            target[r] = offset.float() + grid
            weight[r] = wt.float()

    def all_edges(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(ii, jj)`` of the active edges followed by the retired ones (for the final global BA)."""
        rii, rjj = self.retired_edges()
        return torch.cat([self.ii, rii]), torch.cat([self.jj, rjj])

    def edge_id_pairs(self) -> list[tuple[int, int]]:
        """``(src id, dst id)`` of every edge, active and retired (stable ids)."""
        ids = self._ids[: self.n]
        pairs = list(zip(ids[self.ii].tolist(), ids[self.jj].tolist())) if self.ii.numel() else []
        return pairs + list(self._retired)

    def retired_bytes(self) -> int:
        """Bytes of the retired edges' stored observations (in memory, or in the spill store's file)."""
        h, w = self.ba_shape
        return len(self._retired) * 2 * (2 * h * w) * 2  # offset and weight, [2, h, w] float16 each

    # ------------------------------------------------------------------------------------------- state
    def set_poses(self, idx, poses_wc: torch.Tensor) -> None:
        idx = torch.as_tensor(idx, device=self.device)
        self._poses[: self.n][idx] = torch.as_tensor(poses_wc).to(self.device, torch.float64)

    def set_disps(self, idx, disps: torch.Tensor) -> None:
        idx = torch.as_tensor(idx, device=self.device)
        self._disps[: self.n][idx] = torch.as_tensor(disps).to(self.device, torch.float32)

    def frame_distance(self, ii, jj, beta: float = 0.3) -> torch.Tensor:
        """DROID frame distance ``[E]`` for edges ``ii -> jj`` under the current estimate (BA-resolution pixels)."""
        ii = torch.as_tensor(ii, dtype=torch.int64, device=self.device).reshape(-1)
        jj = torch.as_tensor(jj, dtype=torch.int64, device=self.device).reshape(-1)
        return _frame_distance(self.poses, self.disps, self.intrinsics, ii, jj, beta=beta)

    def mutual_distance(self, k: int, cands) -> torch.Tensor:
        """float ``[C]`` (CPU): the mean of the frame distances ``k -> c`` and ``c -> k`` for each of the graph
        indices ``cands``."""
        cand = torch.as_tensor(cands, dtype=torch.int64).reshape(-1)
        src = torch.full_like(cand, int(k))
        return 0.5 * (self.frame_distance(src, cand).cpu() + self.frame_distance(cand, src).cpu())

    def state_dict(self) -> dict[str, Any]:
        """Keyframes and active edges (the retired store and recorded observations are not included)."""
        return {
            "ba_shape": torch.tensor(self.ba_shape, dtype=torch.int64),
            "intrinsics": self.intrinsics.cpu().clone(),
            "poses": self.poses.cpu().clone(),
            "disps": self.disps.cpu().clone(),
            "frame_index": self.frame_index.cpu().clone(),
            "timestamps": self.timestamps.cpu().clone(),
            "ids": self.ids.cpu().clone(),
            "next_id": torch.tensor(self.next_id, dtype=torch.int64),
            "ii": self.ii.cpu().clone(),
            "jj": self.jj.cpu().clone(),
            "edge_age": self.edge_age.cpu().clone(),
            "edge_kind": self.edge_kind.cpu().clone(),
            "edge_born": self.edge_born.cpu().clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        h, w = (int(v) for v in state["ba_shape"].tolist())
        n = int(state["poses"].shape[0])
        self.ba_shape = (h, w)
        self.intrinsics = state["intrinsics"].to(self.device, torch.float32).clone()
        cap = max(1, self.capacity)
        while cap < n:
            cap *= 2
        self._poses = torch.zeros(cap, 7, dtype=torch.float64, device=self.device)
        self._disps = torch.zeros(cap, h, w, dtype=torch.float32, device=self.device)
        self._frame_index = torch.zeros(cap, dtype=torch.int64, device=self.device)
        self._timestamps = torch.zeros(cap, dtype=torch.float64, device=self.device)
        self._ids = torch.zeros(cap, dtype=torch.int64, device=self.device)
        self.n = n
        self._poses[:n] = state["poses"].to(self.device, torch.float64)
        self._disps[:n] = state["disps"].to(self.device, torch.float32)
        self._frame_index[:n] = state["frame_index"].to(self.device)
        self._timestamps[:n] = state["timestamps"].to(self.device, torch.float64)
        ids = state.get("ids", torch.arange(n))
        self._ids[:n] = ids.to(self.device, torch.int64)
        self._ids_cpu = [int(v) for v in ids.tolist()]
        self.next_id = int(state.get("next_id", torch.tensor(n)))
        self.ii = state["ii"].to(self.device, torch.int64).clone()
        self.jj = state["jj"].to(self.device, torch.int64).clone()
        self.edge_age = state["edge_age"].to(self.device, torch.int64).clone()
        self.edge_kind = state["edge_kind"].to(self.device, torch.int8).clone()
        self.edge_born = state.get("edge_born", torch.zeros_like(state["ii"])).to(self.device, torch.int64).clone()
        self._last_obs.clear()
        for handle, _kind in self._retired.values():
            self.spill.drop(handle)
        self._retired.clear()

    @classmethod
    def from_state_dict(cls, state: dict[str, Any], device="cpu") -> "FrameGraph":
        h, w = (int(v) for v in state["ba_shape"].tolist())
        g = cls(h, w, state["intrinsics"], device=device, capacity=max(1, int(state["poses"].shape[0])))
        g.load_state_dict(state)
        return g


_GRIDS: dict[tuple[int, int, str], torch.Tensor] = {}


def median_disp_map(graph: Optional["FrameGraph"]) -> Optional[torch.Tensor]:
    """A constant inverse-depth map ``[h, w]`` (BA resolution, float32) at the median of the newest keyframe's
    finite positive inverse depths, or None when there is no such keyframe: a frontend's ``initial_depth`` guess for
    a new keyframe, as DROID-SLAM 2025 does (a median is robust to the few near/far outliers that pull a mean)."""
    if graph is None or int(graph.n) < 1:
        return None
    d = graph.disps[-1]
    d = d[torch.isfinite(d) & (d > 0)]
    if d.numel() == 0:
        return None
    h, w = graph.ba_shape
    return torch.full((int(h), int(w)), float(d.median()), dtype=torch.float32, device=graph.disps.device)


def _grid(h: int, w: int, device: torch.device) -> torch.Tensor:
    """float32 ``[2, h, w]`` pixel coordinates ``(x, y)`` (cached)."""
    key = (h, w, str(device))
    g = _GRIDS.get(key)
    if g is None:
        ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32, device=device),
                                torch.arange(w, dtype=torch.float32, device=device), indexing="ij")
        g = _GRIDS[key] = torch.stack([xs, ys])
    return g
