"""``frontend.plugin = "raft_gru"`` in real pipeline runs (public interface only) on a short synthetic sequence at
192 x 128: it completes and writes a trajectory, the mapper drives ``rounds`` observe -> BA rounds per keyframe, and
the per-edge GRU state follows every retirement and removal the graph announces."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from pvslam_core.api import run_config
from pvslam_core.outputs.trajectory_io import read_tum
from pvslam_core.registry import build_registry, hookimpl
from pvslam_plugins.frontends.raft_gru.config import RaftGruConfig
from pvslam_plugins.frontends.raft_gru.frontend import RaftGruFrontend

FRAMES = 24


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    """Pipeline runs and the trainer set torch's (process-wide) thread count; other tests of the session compare
    against features computed with the default count (bitwise), so it is restored."""
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


class AuditedFrontend(RaftGruFrontend):
    """Checks on every observe that it holds no state the graph does not have (test_seams' audit)."""

    instances: list["AuditedFrontend"] = []

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.errors: list[str] = []
        self.retired: list[tuple[int, int]] = []
        self.removed: list[int] = []
        self.max_state = 0
        self.rounds_seen: dict[int, int] = {}  # newest keyframe id -> observe calls while it was the newest
        AuditedFrontend.instances.append(self)

    def observe(self, graph, ii, jj):
        ids = graph.ids.tolist()
        active = {(ids[i], ids[j]) for i, j in zip(graph.ii.tolist(), graph.jj.tolist())}
        asked = {(ids[i], ids[j]) for i, j in zip(ii.tolist(), jj.tolist())}
        stale = set(self._edges) - active - asked
        if stale:
            self.errors.append(f"state for edges the graph no longer has: {sorted(stale)[:5]}")
        gone = {k for key in self._edges for k in key} - set(ids)
        if gone:
            self.errors.append(f"state for removed keyframes {sorted(gone)}")
        if set(self._kfs) - set(ids) - {self._pending_id()}:
            self.errors.append(f"keyframes kept after removal: {sorted(set(self._kfs) - set(ids))}")
        self.rounds_seen[ids[-1]] = self.rounds_seen.get(ids[-1], 0) + 1
        out = super().observe(graph, ii, jj)
        self.max_state = max(self.max_state, len(self._edges))
        return out

    def _pending_id(self):
        return None

    def on_edges_retired(self, src_ids, dst_ids):
        self.retired += list(zip(src_ids.tolist(), dst_ids.tolist()))
        super().on_edges_retired(src_ids, dst_ids)

    def on_keyframe_removed(self, kf_id):
        self.removed.append(kf_id)
        super().on_keyframe_removed(kf_id)


class AuditPlugin:
    @staticmethod
    @hookimpl
    def register_frontends(register):
        register("raft_gru_audit", lambda c, ctx: AuditedFrontend(c, device=ctx.device, ba_downsample=ctx.ba_downsample),
                 RaftGruConfig, description="test-only", ba_downsample=8)  # raft_gru's fixed stride, as registered


@pytest.fixture(scope="module")
def small_seq(tmp_path_factory):
    from pvslam_plugins.datasets.synthetic.generator import generate

    return generate("driving_loop", tmp_path_factory.mktemp("seq") / "dl", num_frames=FRAMES, width=192, height=128,
                    progress=False)


def _run(tmp_path: Path, seq: Path, *extra: str):
    reg = build_registry(extra_modules=(AuditPlugin,))
    ov = [f'run.output_dir="{(tmp_path / "runs").as_posix()}"', "run.progress=false", f'dataset.path="{seq.as_posix()}"',
          "loop.plugin=none", "vps.plugin=none", 'frontend.weights="random"', "frontend.keyframe_thresh=0.0001",
          *extra]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the random-weights warning (asserted in test_frontend)
        return run_config(None, overrides=ov, registry=reg)


def test_pipeline_run_writes_a_trajectory(tmp_path, small_seq):
    res = _run(tmp_path, small_seq, 'frontend.plugin="raft_gru"', 'frontend.profile="fast"', "frontend.rounds=1",
               "optimizer.final.iters=1")
    traj = Path(res.run_dir) / "trajectory.txt"
    ts, poses = read_tum(traj)
    assert poses.shape == (FRAMES, 7) and np.isfinite(np.asarray(poses)).all()
    assert res.metrics["tracking"]["keyframes_added"] >= FRAMES // 2


def test_state_follows_retirement_and_removal_and_rounds(tmp_path, small_seq, monkeypatch):
    from pvslam_core.slam.keyframes import KeyframePolicy

    # every proposal an ordinary keyframe (none provisional), so that each new keyframe is optimised while newest
    monkeypatch.setattr(KeyframePolicy, "_would_be_redundant", lambda self, pose, timestamp: False)
    AuditedFrontend.instances.clear()
    res = _run(tmp_path, small_seq, 'frontend.plugin="raft_gru_audit"', "frontend.rounds=2", 'frontend.profile="fast"',
               "graph.edges.active_window=3", "graph.init.warmup=3", "graph.keyframes.redundant_thresh=0.3",
               "optimizer.final.iters=1")
    fe = AuditedFrontend.instances[-1]
    assert fe.errors == []
    assert fe.removed and fe.retired, "the run should remove keyframes and retire edges"
    assert res.metrics["tracking"]["retired_edges"] > 0
    # bounded by the window (3 keyframes x (3 neighbour + 2 proximity edges) x 2 directions), not by the run
    assert fe.max_state <= 3 * (3 + 2) * 2, fe.max_state
    # keyframes optimised after initialisation get `rounds` observe calls while they are the newest keyframe
    counts = list(fe.rounds_seen.values())
    assert max(set(counts), key=counts.count) == 2, fe.rounds_seen
    assert res.poses.shape == (FRAMES, 7) and torch.isfinite(res.poses).all()
