"""Keyframe culling on revisits (pvslam_core.slam.revisits): the frames of a culled keyframe held to the keyframe that
holds its view, the candidates a loop gives, and on a loop driven again a map that stops growing while the
trajectory stays as accurate as with every keyframe kept."""
import json
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from pvslam_core.geometry.lie import se3_mul
from pvslam_core.slam.frame_poses import FramePoses
from pvslam_core.slam.graph import FrameGraph
from pvslam_core.slam.revisits import LOOP_REACH, RevisitCulling
from pvslam_core.types import LoopClosure


def _pose(x: float, yaw: float = 0.0) -> torch.Tensor:
    return torch.tensor([x, 0, 0, 0, math.sin(yaw / 2), 0, math.cos(yaw / 2)], dtype=torch.float64)


def _graph(n: int) -> FrameGraph:
    g = FrameGraph(3, 4, torch.tensor([4.0, 4.0, 1.5, 1.0]))
    for k in range(n):
        g.add_keyframe(10 * k, float(k), _pose(0.5 * k), torch.ones(3, 4))
    return g


def test_rehome_keeps_poses_and_then_follows_the_new_anchor():
    g = _graph(4)
    fp = FramePoses(g)
    for k in range(4):
        fp.add_keyframe(10 * k, float(k), g.id_of(k))
        if k == 2:  # two frames tracked against keyframe 2, one held between keyframes 1 and 2
            fp.add_frame(21, 2.1, g.id_of(2), _pose(0.1, 0.05))
            fp.add_frame(22, 2.2, g.id_of(2), _pose(0.2, 0.1))
    held = fp.add_frame(15, 1.5, g.id_of(1), _pose(0.0))
    fp.hold_between(held, g.id_of(1), g.id_of(2), fp.pose_of(held))
    before = fp.poses()[1].clone()
    assert fp.rehome(g.id_of(2), g.id_of(0)) == 4  # keyframe 2's own entry, its two frames, the frame held up to it
    assert torch.allclose(fp.poses()[1], before, atol=1e-12)
    g.remove_keyframe(2)
    assert torch.allclose(fp.poses()[1], before, atol=1e-12)  # nothing was anchored to the removed keyframe
    moved = _pose(0.0, 0.3)
    g.set_poses(torch.tensor([0]), moved[None])  # the new anchor moves: the rehomed frames follow it rigidly
    after = fp.poses()[1]
    rehomed = [n for n, e in enumerate(fp.entries) if e.anchor == g.id_of(0) and n != 0]
    assert len(rehomed) == 4
    for n in rehomed:
        assert torch.allclose(after[n], se3_mul(moved, before[n]), atol=1e-9)


def test_rehome_applies_a_move():
    g = _graph(3)
    fp = FramePoses(g)
    for k in range(3):
        fp.add_keyframe(10 * k, float(k), g.id_of(k))
    fp.add_frame(25, 2.5, g.id_of(2), _pose(0.1))
    before = fp.poses()[1].clone()
    shift = torch.tensor([0.0, 0.25, 0.0], dtype=torch.float64)
    fp.rehome(g.id_of(2), g.id_of(1), lambda p: torch.cat([p[:, :3] + shift, p[:, 3:]], dim=1))
    after = fp.poses()[1]
    assert torch.allclose(after[2:, :3], before[2:, :3] + shift, atol=1e-12)
    assert torch.allclose(after[:2], before[:2], atol=1e-12)  # keyframes 0 and 1 are not touched


def _state(n: int, unmerged: int = 1) -> SimpleNamespace:
    """The map state culling reads: ``n`` keyframes in one fragment; ``unmerged`` > 1 skips the island pass."""
    return SimpleNamespace(graph=_graph(n), fragments=SimpleNamespace(unmerged=unmerged), fragment_start=0,
                           px_scale=1.0)


def test_candidates_are_the_old_keyframes_near_a_nearby_loop_partner():
    loops = [LoopClosure(frame_i=600, frame_j=50, kf_i=60, kf_j=5, score=0.9, verified=True)]
    cull = RevisitCulling(4.0, _state(80), observer=None, active_window=10, loops=loops)
    assert cull.candidates(60 + LOOP_REACH + 1) == []  # no loop within reach of it
    near = cull.candidates(64)
    assert near == list(range(0, 5 + LOOP_REACH + 1))  # around the partner, keyframe 5
    # a partner within the window before the keyframe gives nothing of that window
    loops.append(LoopClosure(frame_i=700, frame_j=650, kf_i=70, kf_j=62, score=0.9, verified=True))
    assert max(cull.candidates(72)) < 72 - 10


def test_keyframes_cut_off_from_the_map_are_culled_and_their_frames_stay():
    st = _state(30)
    g = st.graph
    st.frames = fp = FramePoses(g)
    for k in range(30):
        fp.add_keyframe(10 * k, float(k), g.id_of(k))
        fp.add_frame(10 * k + 5, k + 0.5, g.id_of(k), _pose(0.1))
    chain = [(k, k + 1) for k in range(19)] + [(19, 24)] + [(k, k + 1) for k in range(24, 29)]
    island = [(21, 22), (22, 23)]  # 20 has no edge at all; 21-23 only among themselves
    ii, jj = zip(*(chain + island))
    g.add_edges(torch.tensor(ii), torch.tensor(jj))
    before = fp.poses()[1].clone()
    cull = RevisitCulling(4.0, st, observer=None, active_window=5, loops=[])
    assert cull._cull_islands() == 4
    assert g.n == 26 and cull.culled == 4
    assert torch.allclose(fp.poses()[1], before, atol=1e-12)  # every frame stays where it was
    anchors = {e.anchor for e in fp.entries}
    assert anchors <= set(g.ids.tolist()) and g.id_of(19) in anchors
    assert cull._cull_islands() == 0  # nothing left to cut off


def _stream(n: int, failing: set[int], stayed: bool = False):
    """Keyframes added one by one with a settled loop near the start; examination fails the gates of the ids in
    ``failing`` (and passes the others).  Returns the ids kept (with ``stayed``: and the ids culling remembers as a
    revisit's stretch)."""
    st = _state(0, unmerged=2)  # no island pass: only the decision under test
    g = st.graph

    class _Culling(RevisitCulling):
        def _examine(self, r):
            return g.id_of(r) - 1, None, 1.0, g.id_of(r) not in failing

        def _cull(self, r_id, j_id, rel, scale):
            g.remove_keyframe(g.index_of(r_id))
            self.culled += 1
            return True

    loops = [LoopClosure(frame_i=120, frame_j=20, kf_i=12, kf_j=2, score=0.9, verified=True, loop_ba=True)]
    cull = _Culling(4.0, st, observer=None, active_window=5, loops=loops, neighbours=3)
    for k in range(n):
        g.add_keyframe(10 * k, float(k), _pose(0.5 * k), torch.ones(3, 4))
        cull.cull(g.n - 1)
    return (set(g.ids.tolist()), cull._stayed) if stayed else set(g.ids.tolist())


def test_an_isolated_failed_gate_does_not_keep_a_stretch():
    n = 60
    settled = set(range(23, n - 10))  # examined once the loop settled, decided before the run ended
    # one bad relocalisation amid agreeing ones: it goes too, and so do its neighbours
    assert not _stream(n, failing={30}) & settled
    # two in a row (a lap's junction): they stay, with their odometry neighbours on either side
    kept, stayed = _stream(n, failing={30, 31}, stayed=True)
    assert set(range(27, 35)) <= kept and not kept & (settled - set(range(27, 35)))
    # the whole stretch, its failed keyframes and the neighbours they kept, is what a later revisit may go for
    assert stayed == set(range(27, 35))


# ------------------------------------------------------------------------------- a loop driven again --
LAPS = 2.6  # driving_block: about 210 frames a lap


def _run(out: Path, *extra: str):
    from pvslam_core.api import run_config
    from pvslam_plugins.datasets.synthetic.generator import generate

    seq = generate("driving_block", None, laps=LAPS, progress=False)
    res = run_config(None, overrides=[f'run.output_dir="{out.as_posix()}"', "run.progress=false",
                                      f'dataset.path="{seq.as_posix()}"', "outputs.ply=false", "outputs.plots=false",
                                      "segmenter.plugin=none", "vps.plugin=none", *extra])
    assert not res.metrics.get("failed"), res.metrics
    keyframes = json.loads((Path(res.run_dir) / "metrics.json").read_text())["tracking"]
    return res, keyframes


@pytest.fixture(scope="module")
def laps_runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("revisits")
    return _run(out / "on", "graph.keyframes.revisit_thresh=4"), _run(out / "off")


def _bounded(tracking: dict) -> bool:
    """The revisits of 2.6 laps culled: at most 75 % of the keyframes the map would keep without culling (68 % kept
    with culling; without it every one, 100 %)."""
    kept = tracking["keyframes_added"] - tracking["keyframes_removed"]
    redundant = tracking["keyframes_removed"] - tracking["keyframes_culled_on_revisits"]
    return kept <= 0.75 * (tracking["keyframes_added"] - redundant)


@pytest.mark.slow
def test_revisits_keep_the_map_bounded_and_the_trajectory_accurate(laps_runs):
    (on, t_on), (off, t_off) = laps_runs
    assert t_on["keyframes_culled_on_revisits"] > 0
    assert _bounded(t_on), t_on
    ate_on = on.metrics["ate"]["rmse_percent_of_path"]
    ate_off = off.metrics["ate"]["rmse_percent_of_path"]
    assert ate_on <= 1.25 * ate_off + 0.02, (ate_on, ate_off)  # percent of the path
    assert on.metrics["tracking"]["maps"] == 1


@pytest.mark.slow
def test_the_bound_fails_without_culling(laps_runs):
    _, (_, t_off) = laps_runs
    assert t_off["keyframes_culled_on_revisits"] == 0
    assert not _bounded(t_off), t_off


def _examiner(monkeypatch, scales: dict, agree: set, stayed: set, dist: dict):
    """A culling whose keyframe 20 has the candidates in ``dist`` (graph index -> frame distance, BA px); the
    relocalisation against candidate j gives scale ``scales[j]`` and the current estimate explains the flow for the
    candidates in ``agree``; ``stayed``: candidates that stayed on an earlier revisit."""
    st = _state(30)
    g = st.graph
    cands = sorted(dist)
    monkeypatch.setattr(g, "mutual_distance", lambda r, cs: torch.tensor([dist[c] for c in cs]))
    monkeypatch.setattr("pvslam_core.slam.revisits.relocalise", lambda pose_j, disp_j, *a: SimpleNamespace(
        pose=_pose(float(pose_j[0]) + 0.1), scale=scales[int(round(float(pose_j[0]) / 0.5))], error=0.0))
    monkeypatch.setattr("pvslam_core.slam.revisits.median_error", lambda pose_j, *a: (
        0.0 if int(round(float(pose_j[0]) / 0.5)) in agree else 1.0))
    observer = SimpleNamespace(observe_pair=lambda j, r: SimpleNamespace(target=[None], weight=[None]))
    cull = RevisitCulling(4.0, st, observer=observer, active_window=5, loops=[])
    monkeypatch.setattr(cull, "candidates", lambda r: cands)
    cull._stayed = {g.id_of(j) for j in stayed}
    return cull, g


def test_a_revisit_keyframe_tries_the_nearest_views_and_a_place_keeps_one_stretch(monkeypatch):
    # the nearest view disagrees, the second agrees: r goes for the second, where its relocalisation puts it
    cull, g = _examiner(monkeypatch, {3: 1.0, 5: 1.0, 7: 1.0}, agree={5}, stayed=set(), dist={3: 0.5, 5: 1.0, 7: 2.0})
    j_id, rel, scale, passed = cull._examine(20)
    assert passed and j_id == g.id_of(5) and torch.allclose(rel[:3], torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64))
    # no view agrees and none stayed before: r fails (and stays with its neighbours, step 4)
    cull, g = _examiner(monkeypatch, {3: 1.0, 5: 1.0}, agree=set(), stayed=set(), dist={3: 0.5, 5: 1.0})
    assert cull._examine(20)[3] is False
    # no view agrees, but one of them stayed on an earlier revisit and agrees on the scale: r goes for it
    cull, g = _examiner(monkeypatch, {3: 1.0, 5: 1.02}, agree=set(), stayed={5}, dist={3: 0.5, 5: 1.0})
    j_id, rel, scale, passed = cull._examine(20)
    assert passed and j_id == g.id_of(5) and scale == 1.02
    # ... unless its scale disagrees too: r stays
    cull, g = _examiner(monkeypatch, {3: 1.0, 5: 1.3}, agree=set(), stayed={5}, dist={3: 0.5, 5: 1.0})
    assert cull._examine(20)[3] is False
    # views beyond the threshold or past MAX_TRIES are not tried
    cull, g = _examiner(monkeypatch, {3: 1.0, 5: 1.0, 7: 1.0, 9: 1.0}, agree={9}, stayed=set(),
                        dist={3: 0.5, 5: 1.0, 7: 2.0, 9: 3.0})
    assert cull._examine(20)[3] is False  # 9 is the fourth nearest
    cull, g = _examiner(monkeypatch, {3: 1.0}, agree={3}, stayed=set(), dist={3: 4.5})
    assert cull._examine(20) is None
