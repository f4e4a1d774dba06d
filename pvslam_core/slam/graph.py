"""The frame graph: keyframe store (pose, inverse depth at the BA resolution) plus directed edges ``i -> j``.

Storage grows geometrically (amortised O(1) ``add_keyframe``); the public attributes are views of the first
``n`` rows.  Memory per keyframe is one pose plus one ``h x w`` inverse-depth map.  Poses are ``T_wc``
(camera-to-world, float64), see :mod:`pvslam_core.types`.
"""
from __future__ import annotations

from typing import Any

import torch

from ..geometry.projective import frame_distance as _frame_distance

EDGE_ODOMETRY = 0  # odometry / neighbourhood edge
EDGE_PROXIMITY = 1
EDGE_LOOP = 2


class FrameGraph:
    def __init__(self, ba_height: int, ba_width: int, intrinsics: torch.Tensor, device="cpu", capacity: int = 64):
        self.device = torch.device(device)
        self.ba_shape = (int(ba_height), int(ba_width))
        self.intrinsics = torch.as_tensor(intrinsics, dtype=torch.float32).to(self.device).reshape(4).clone()
        capacity = max(1, int(capacity))
        self.n = 0
        h, w = self.ba_shape
        self._poses = torch.zeros(capacity, 7, dtype=torch.float64, device=self.device)
        self._disps = torch.zeros(capacity, h, w, dtype=torch.float32, device=self.device)
        self._frame_index = torch.zeros(capacity, dtype=torch.int64, device=self.device)
        self._timestamps = torch.zeros(capacity, dtype=torch.float64, device=self.device)
        self.ii = torch.zeros(0, dtype=torch.int64, device=self.device)
        self.jj = torch.zeros(0, dtype=torch.int64, device=self.device)
        self.edge_age = torch.zeros(0, dtype=torch.int64, device=self.device)
        self.edge_kind = torch.zeros(0, dtype=torch.int8, device=self.device)

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
    def num_edges(self) -> int:
        return int(self.ii.shape[0])

    def __len__(self) -> int:
        return self.n

    def __repr__(self) -> str:
        return f"FrameGraph(n={self.n}, edges={self.num_edges}, ba_shape={self.ba_shape}, device={self.device})"

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

    def add_keyframe(self, frame_index: int, timestamp: float, pose_wc: torch.Tensor, disp: torch.Tensor) -> int:
        """Append a keyframe; returns its index (``n - 1`` afterwards)."""
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
        self.n += 1
        return k

    def remove_keyframe(self, k: int) -> None:
        """Remove keyframe ``k`` and the edges touching it; later keyframes (and edge ends) shift down by one."""
        k = int(k)
        if not 0 <= k < self.n:
            raise IndexError(f"keyframe {k} out of range (n={self.n})")
        for buf in (self._poses, self._disps, self._frame_index, self._timestamps):
            buf[k : self.n - 1] = buf[k + 1 : self.n].clone()
        self.n -= 1
        keep = (self.ii != k) & (self.jj != k)
        self._keep_edges(keep)
        self.ii = self.ii - (self.ii > k).long()
        self.jj = self.jj - (self.jj > k).long()

    # ------------------------------------------------------------------------------------------- edges
    def _keep_edges(self, keep: torch.Tensor) -> None:
        self.ii, self.jj = self.ii[keep], self.jj[keep]
        self.edge_age, self.edge_kind = self.edge_age[keep], self.edge_kind[keep]

    def has_edges(self, ii, jj) -> torch.Tensor:
        """bool ``[len(ii)]``: whether each ``ii -> jj`` is already an edge."""
        ii = torch.as_tensor(ii, dtype=torch.int64, device=self.device).reshape(-1)
        jj = torch.as_tensor(jj, dtype=torch.int64, device=self.device).reshape(-1)
        if self.num_edges == 0 or len(ii) == 0:
            return torch.zeros(len(ii), dtype=torch.bool, device=self.device)
        m = max(self.n, int(ii.max()) + 1, int(jj.max()) + 1, int(self.ii.max()) + 1, int(self.jj.max()) + 1)
        existing = self.ii * m + self.jj
        return torch.isin(ii * m + jj, existing)

    def add_edges(self, ii, jj, kind: int = EDGE_ODOMETRY) -> torch.Tensor:
        """Add edges ``ii -> jj``; self-edges, out-of-range ends and duplicates (with existing edges or within the
        call) are skipped.  Returns the bool mask ``[len(ii)]`` of edges actually added (new edges have age 0)."""
        ii = torch.as_tensor(ii, dtype=torch.int64, device=self.device).reshape(-1)
        jj = torch.as_tensor(jj, dtype=torch.int64, device=self.device).reshape(-1)
        if ii.shape != jj.shape:
            raise ValueError(f"ii and jj differ in length: {tuple(ii.shape)} vs {tuple(jj.shape)}")
        ok = (ii != jj) & (ii >= 0) & (jj >= 0) & (ii < self.n) & (jj < self.n)
        ok &= ~self.has_edges(ii, jj)
        if ok.any():
            # duplicates inside this call: keep the first occurrence
            key = ii * max(self.n, 1) + jj
            idx = torch.nonzero(ok).squeeze(1)
            _, inv = torch.unique(key[idx], return_inverse=True)
            first = torch.full((int(inv.max()) + 1,), len(idx), dtype=torch.int64, device=self.device)
            first.scatter_reduce_(0, inv, torch.arange(len(idx), device=self.device), reduce="amin")
            keep_idx = idx[first]
            ok = torch.zeros_like(ok)
            ok[keep_idx] = True
        sel = torch.nonzero(ok).squeeze(1)
        if len(sel):
            self.ii = torch.cat([self.ii, ii[sel]])
            self.jj = torch.cat([self.jj, jj[sel]])
            self.edge_age = torch.cat([self.edge_age, torch.zeros(len(sel), dtype=torch.int64, device=self.device)])
            self.edge_kind = torch.cat(
                [self.edge_kind, torch.full((len(sel),), int(kind), dtype=torch.int8, device=self.device)]
            )
        return ok

    def remove_edges(self, mask: torch.Tensor) -> None:
        """Remove the edges where ``mask`` (bool over the current edges) is True."""
        mask = torch.as_tensor(mask, dtype=torch.bool, device=self.device).reshape(-1)
        if mask.shape[0] != self.num_edges:
            raise ValueError(f"mask has {mask.shape[0]} entries for {self.num_edges} edges")
        self._keep_edges(~mask)

    def age_edges(self, by: int = 1) -> None:
        self.edge_age = self.edge_age + int(by)

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

    def state_dict(self) -> dict[str, Any]:
        return {
            "ba_shape": torch.tensor(self.ba_shape, dtype=torch.int64),
            "intrinsics": self.intrinsics.cpu().clone(),
            "poses": self.poses.cpu().clone(),
            "disps": self.disps.cpu().clone(),
            "frame_index": self.frame_index.cpu().clone(),
            "timestamps": self.timestamps.cpu().clone(),
            "ii": self.ii.cpu().clone(),
            "jj": self.jj.cpu().clone(),
            "edge_age": self.edge_age.cpu().clone(),
            "edge_kind": self.edge_kind.cpu().clone(),
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
        self.n = n
        self._poses[:n] = state["poses"].to(self.device, torch.float64)
        self._disps[:n] = state["disps"].to(self.device, torch.float32)
        self._frame_index[:n] = state["frame_index"].to(self.device)
        self._timestamps[:n] = state["timestamps"].to(self.device, torch.float64)
        self.ii = state["ii"].to(self.device, torch.int64).clone()
        self.jj = state["jj"].to(self.device, torch.int64).clone()
        self.edge_age = state["edge_age"].to(self.device, torch.int64).clone()
        self.edge_kind = state["edge_kind"].to(self.device, torch.int8).clone()

    @classmethod
    def from_state_dict(cls, state: dict[str, Any], device="cpu") -> "FrameGraph":
        h, w = (int(v) for v in state["ba_shape"].tolist())
        g = cls(h, w, state["intrinsics"], device=device, capacity=max(1, int(state["poses"].shape[0])))
        g.load_state_dict(state)
        return g
