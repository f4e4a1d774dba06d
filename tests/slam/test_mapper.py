"""The mapper (Algorithm 1's per-frame driver) with the framework's exact fake plugins: per-frame results,
initialisation, online BA accuracy, loop handling, keyframe removal, the motion cue for the VPS head, and the
measured / guessed depth pixels (pvslam_core/slam/observed.py) in a keyframe's pose guess."""
import dataclasses
import math

import pytest
import torch

import fakes
from pvslam_core.adapt import REF_BA_FOCAL
from pvslam_core.config import validate_pipeline
from pvslam_core.geometry.lie import se3_exp, se3_inv, se3_mul
from pvslam_core.geometry.projective import edge_transforms, project_points
from pvslam_core.geometry.testing import umeyama_ate
from pvslam_core.interfaces import BuildContext
from pvslam_core.registry import get_registry
from pvslam_core.slam import keyframes, loops, new_keyframe, observed, revisits
from pvslam_core.slam.graph import EDGE_LOOP
from pvslam_core.slam.mapper import Mapper
from pvslam_core.slam.motion_cue import motion_cue
from pvslam_core.types import TrackResult


SPEED = 0.4  # m per frame: 2.5 / 1.25 BA px between keyframes on the near / far plane (enough parallax)


@pytest.fixture(autouse=True)
def _no_loop_suppression(monkeypatch):
    monkeypatch.setattr(loops, "NMS_KEYFRAMES", 0)  # every keyframe may close a loop


FAKE_PER_REF = REF_BA_FOCAL / (fakes.F / 4)  # reference BA px per BA px of the fake camera (f = 10 BA px at 1/4)


@pytest.fixture(autouse=True)
def _redundancy_gate_in_fake_px(monkeypatch):
    """The redundancy test's quantile gate at 4 BA px of the fake camera, as these tests were written (the constant
    is in reference BA px: an angle of view)."""
    monkeypatch.setattr(keyframes, "REDUNDANT_MAX_FLOW", 4.0 * FAKE_PER_REF)


def build(frames=24, loop=None, optimizer="online_ba", redundant_thresh=0.0, edges=None):
    """A mapper over the exact fakes; ``redundant_thresh`` in the fake camera's BA px (0: every keyframe stays)."""
    ref_px = redundant_thresh * FAKE_PER_REF  # the config's unit: reference BA px (an angle)
    pcfg = validate_pipeline({"graph": {"init": {"warmup": 3}, "ba_downsample": 4,
                                        "keyframes": {"redundant_thresh": ref_px}, "edges": edges or {}}})
    ds = fakes.FakeDataset(fakes.FakeDatasetConfig(frames=frames, speed=SPEED))
    fe = fakes.ExactFrontend(fakes.ExactFrontendConfig(keyframe_every=2), ds=4)
    spec = get_registry().get("optimizer", optimizer)
    opt = spec.factory(spec.config_model(), BuildContext(device=torch.device("cpu")))
    return Mapper(pcfg, ds.info(), fe, opt, loop, "cpu"), ds, fe


def test_results_initialisation_and_accuracy():
    m, ds, fe = build()
    results = [m.process(f, None) for f in ds]
    first = results[0]
    assert first.keyframe_id == 0 and first.ref_id is None and first.is_keyframe
    assert [r.is_keyframe for r in results[:6]] == [True, False, True, False, True, False]  # every 2nd frame
    r1 = results[1]  # tracked against keyframe 0
    assert r1.ref_id == 0 and r1.ref_target.shape == (2, 12, 16) and r1.keyframe_id is None
    assert not results[2].initialized and results[4].initialized  # warmup = 3 keyframes
    assert results[5].ref_id == 2  # the third keyframe
    m.finalize()
    ts, poses = m.trajectory()
    gt = torch.stack([f.gt_pose for f in ds])
    assert len(ts) == len(gt)
    ate = umeyama_ate(poses[:, :3], gt[:, :3])
    assert ate < 1e-3 * float((gt[-1, :3] - gt[0, :3]).norm()), ate  # exact targets: exact poses up to scale


def test_motion_cue_between_frames_sharing_a_reference():
    m, ds, fe = build(frames=14)
    frames = list(ds)
    results = [m.process(f, None) for f in frames]
    prev, cur = results[10], results[11]  # keyframe 10 (reference) -> frame 11
    assert prev.keyframe_id is not None and cur.ref_id == prev.keyframe_id
    cue = motion_cue(prev, cur)
    h, w = 12, 16
    f = fakes.F / 4
    z = fakes.depth_map(h, w)
    true_u = -f * SPEED / z  # the camera moves +x by SPEED per frame
    ok = cue.flow_valid
    assert ok.float().mean() > 0.8
    assert torch.allclose(cue.flow[0][ok], true_u[ok], atol=1e-3) and float(cue.flow[1].abs().max()) < 1e-3
    # depth of the previous frame, in map units (monocular scale): the far plane is twice as far
    d = cue.depth_prev
    assert abs(float(d[:, -3].median() / d[:, 2].median()) - 2.0) < 0.01
    assert cue.pose_prev is not None and cue.intrinsics is not None
    # two non-keyframes sharing the reference: the flow between them follows from both targets
    m2, ds2, _ = build(frames=14)
    fe2 = m2.frontend
    fe2.cfg.keyframe_every = 3
    rs = [m2.process(f_, None) for f_ in ds2]
    pairs = [(a, b) for a, b in zip(rs, rs[1:]) if a.ref_id is not None and a.ref_id == b.ref_id and not a.is_keyframe]
    assert pairs
    cue = motion_cue(*pairs[-1])
    ok = cue.flow_valid.clone()
    ok[:, w // 2 - 2: w // 2 + 2] = False  # the fake planes are fixed in the image, not in 3D: skip their border
    assert ok.float().mean() > 0.5
    assert torch.allclose(cue.flow[0][ok], true_u[ok], atol=1e-3)
    assert motion_cue(None, cur).flow is None


class VerifiedLoop:
    """Proposes (id, 1) from keyframe id 8 on (a stand-in detector)."""

    def __init__(self):
        self.added = []

    def add_keyframe(self, kf_id, frame):
        self.added.append(kf_id)

    def query(self, kf_id, skip=None):
        from pvslam_core.types import LoopCandidate

        return [LoopCandidate(kf_id, 1, 0.9, verified=True, inliers=50)] if kf_id >= 8 else []

    def on_keyframe_removed(self, kf_id):
        self.added.remove(kf_id)

    def on_edges_retired(self, src, dst):
        pass


def test_loops_add_edges_and_run_the_loop_ba():
    det = VerifiedLoop()
    m, ds, fe = build(frames=24, loop=det)
    for f in ds:
        m.process(f, None)
    assert det.added == m.graph.ids.tolist()
    assert m.loops and m.loops[0].kf_i == 8 and m.loops[0].kf_j == 1 and m.loops[0].loop_ba
    g = m.graph
    loop_pairs = {(int(g.ids[i]), int(g.ids[j])) for i, j, k in zip(g.ii, g.jj, g.edge_kind) if int(k) == EDGE_LOOP}
    # later loop edges are still active; the first loop's have retired with their keyframe's window
    assert {(11, 0), (11, 1), (11, 2)} <= loop_pairs | {(a, b) for a, b in [(11, 0), (11, 1), (11, 2)]}
    assert g.num_retired > 0


def test_redundant_keyframes_are_removed_and_everyone_hears():
    m, ds, fe = build(frames=30, redundant_thresh=2.2)
    for f in ds:
        m.process(f, None)
    ids = m.graph.ids.tolist()
    assert len(ids) < 15  # 15 keyframes were added
    assert sorted(fe.kf_x) == ids and sorted(m.state.images) == ids
    anchors = {e.anchor for e in m.state.frames.entries}
    assert anchors <= set(ids)
    m.finalize()
    assert m.trajectory()[1].shape == (30, 7)


class _CountingOptimizer:
    """Wraps an optimizer and records the graph size at each window BA."""

    def __init__(self, inner):
        self.inner = inner
        self.window_sizes = []

    def step(self, graph, obs):
        self.window_sizes.append(graph.n)
        return self.inner.step(graph, obs)

    def __getattr__(self, name):
        return getattr(self.inner, name)


def _run_counted(frames, loop=None):
    m, ds, fe = build(frames=frames, loop=loop, redundant_thresh=2.2)
    m.window_ba.optimizer = _CountingOptimizer(m.window_ba.optimizer)
    provisional_had_edges = []
    for f in ds:
        r = m.process(f, None)
        if m.keyframe_policy.provisional is not None:  # the newest keyframe is provisional: no edge touches it yet
            k = m.graph.index_of(m.keyframe_policy.provisional)
            provisional_had_edges.append(bool(((m.graph.ii == k) | (m.graph.jj == k)).any()))
    return m, ds, fe, provisional_had_edges


def test_provisional_keyframes_skip_the_work_of_redundant_ones(monkeypatch):
    """Keyframes that would be removed as redundant right after their BA stay provisional (no edges, no BA) and
    are removed when the next keyframe comes: fewer window BAs, the same kind of map, exact poses still.  (The
    reference: every proposal ordinary, removed after its BA when redundant.)"""
    with monkeypatch.context() as mp:
        mp.setattr(keyframes.KeyframePolicy, "_would_be_redundant", lambda self, pose, ts: False)
        m0, ds, _, _ = _run_counted(30)
    m1, ds, fe, had_edges = _run_counted(30)
    assert had_edges and not any(had_edges)  # provisional keyframes existed and never had edges
    assert m1.keyframe_policy.provisional_removed > 0 and m0.keyframe_policy.provisional_removed == 0
    assert len(m1.window_ba.optimizer.window_sizes) < len(m0.window_ba.optimizer.window_sizes)  # the point
    ids = m1.graph.ids.tolist()
    assert abs(len(ids) - len(m0.graph.ids)) <= 2  # about as many keyframes stay as with removal after the BA
    assert sorted(fe.kf_x) == ids and sorted(m1.state.images) == ids  # everyone heard of the removals
    assert {e.anchor for e in m1.state.frames.entries} <= set(ids)
    m1.finalize()
    ts, poses = m1.trajectory()
    gt = torch.stack([f.gt_pose for f in ds])
    assert len(ts) == len(gt) and m1.keyframe_policy.provisional is None
    ate = umeyama_ate(poses[:, :3], gt[:, :3])
    assert ate < 1e-3 * float((gt[-1, :3] - gt[0, :3]).norm()), ate


def test_provisional_keyframe_that_is_not_redundant_becomes_ordinary():
    """With a threshold between the guessed and the optimised distances nothing is lost: every keyframe ends up
    either removed or connected, and the loop detector heard of each one (it is told of every removal)."""
    det = VerifiedLoop()
    m, ds, fe, _ = _run_counted(24, loop=det)
    g = m.graph
    last = g.n - 1 if m.keyframe_policy.provisional is None else g.n - 2
    for k in range(1, last + 1):  # every settled keyframe has edges
        assert bool(((g.ii == k) | (g.jj == k)).any()), k
    assert det.added == g.ids.tolist()


class _RecordingOptimizer(_CountingOptimizer):
    """Also records, per window BA, the edges it was given and the graph's active edges at that moment."""

    def __init__(self, inner):
        super().__init__(inner)
        self.calls = []

    def step(self, graph, obs):
        active = set(zip(graph.ii.tolist(), graph.jj.tolist()))
        self.calls.append((graph.n, list(zip(obs.ii.tolist(), obs.jj.tolist())), active))
        return super().step(graph, obs)


def test_window_ba_observes_the_active_edges_only():
    """Every window BA is given the active edges of its window, never the stored observations of retired ones
    (they are for the final BA)."""
    window = 3
    m, ds, _ = build(frames=30, edges={"active_window": window, "neighbours": 2})
    m.window_ba.optimizer = _RecordingOptimizer(m.window_ba.optimizer)
    for f in ds:
        m.process(f, None)
    assert m.graph.num_retired > 0
    for n, edges, active in m.window_ba.optimizer.calls:
        assert all(e in active for e in edges), (n, edges)
    m.finalize()
    ts, poses = m.trajectory()
    gt = torch.stack([f.gt_pose for f in ds])
    ate = umeyama_ate(poses[:, :3], gt[:, :3])
    assert ate < 1e-3 * float((gt[-1, :3] - gt[0, :3]).norm()), ate  # exact stored targets keep exact poses


@pytest.mark.parametrize("frac", [0.0, 0.25])
def test_a_new_keyframe_turned_on_the_spot_gets_its_floor_from_the_rows(frac, monkeypatch):
    """new_keyframe.warped_depth moves the previous keyframe's depth into the new one; the columns a turn on the spot
    brings in are holes.  With new_keyframe.FILL_ROW_MIN_FRAC they take their row's depth, which is exact for a floor
    seen by a level camera; with 0 the image's median (the old rule), which is not."""
    monkeypatch.setattr(new_keyframe, "FILL_ROW_MIN_FRAC", frac)
    m, ds, fe = build(frames=4)
    for f in ds:
        m.process(f, None)
    g = m.graph
    h, w = g.ba_shape
    fx, fy, cx, cy = g.intrinsics.tolist()
    v = torch.arange(h, dtype=torch.float32)[:, None].expand(h, w)
    pitch = torch.atan(torch.tensor(cy / fy)) + 0.2  # down, so that the floor fills the view
    down = torch.stack([torch.tensor(0.0), torch.cos(pitch), torch.sin(pitch)])  # the world's down in the camera
    floor = ((v - cy) / fy * down[1] + down[2]) / 1.5  # the floor 1.5 below: by row only
    assert float(floor.min()) > 0
    g.set_disps(torch.tensor([0]), floor[None])
    g.set_poses(torch.tensor([0]), torch.tensor([[0, 0, 0, 0, 0, 0, 1.0]], dtype=g.poses.dtype))
    turn = torch.cat([torch.zeros(3), 0.15 * down]).double()[None]  # a turn about the world's vertical
    yaw = se3_exp(turn)[0]
    disp, _known = new_keyframe.warped_depth(m.state, 0, se3_mul(g.poses[0].double().cpu(), yaw))
    # a turn about the vertical keeps the floor's depth a function of the row: the truth in the new view is `floor`
    err = (disp - floor).abs() / floor
    new_cols = err[:, -3:] if float(err[:, -3:].mean()) > float(err[:, :3].mean()) else err[:, :3]
    if frac > 0:
        assert float(new_cols.max()) < 0.1 and float(err.mean()) < 0.03  # the splat's rounding (measured 0.08)
    else:
        assert float(new_cols.mean()) > 0.2  # the median is far from the near rows and the far ones (measured 0.33)


def test_a_turned_keyframe_inherits_the_measured_pixels_and_not_the_new_columns(monkeypatch):
    monkeypatch.setattr(observed, "UNOBSERVED_WEIGHT", 0.1)
    m, ds, fe = build(frames=8)
    for f in ds:
        m.process(f, None)
    g = m.graph
    h, w = g.ba_shape
    a_id = g.id_of(g.n - 1)
    assert bool(m.state.observed.masks[a_id].all())  # initialised: the triangulation measured every pixel
    half = torch.ones(h, w, dtype=torch.bool)
    half[: h // 2] = False  # the upper half only guessed
    m.state.observed.set(a_id, half)
    yaw = se3_exp(torch.tensor([[0, 0, 0, 0, 0.2, 0]], dtype=torch.float64))[0]  # about the camera's y axis
    disp, known = new_keyframe.warped_depth(m.state, g.n - 1, se3_mul(g.poses[-1].double().cpu(), yaw))
    assert float(disp.min()) > 0  # the holes are filled ...
    new_cols = known[:, -3:] if not bool(known[:, -3:].any()) else known[:, :3]
    assert not bool(new_cols.any())  # ... but the columns the turn brings in are not measured
    assert not bool(known[: h // 2].any())  # the guessed half stays guessed where it lands
    assert float(known[h // 2 + 1:].float().mean()) > 0.6  # the measured half stays measured (less the new columns)


@pytest.mark.parametrize("guess_min, weight, off", [(1.0, 1.0, True),  # all pixels at full weight
                                                     (1.0, 0.1, True),  # down-weighted: still dragged
                                                     (0.3, 1.0, False),  # half measured >= 0.3: those only
                                                     (0.6, 0.1, True)])  # too few measured: all, weighted
def test_guessed_pixels_are_left_out_of_the_keyframe_pose_guess(guess_min, weight, off, monkeypatch):
    """The newest keyframe's upper half is guessed 3x too near (a filled hole) and not measured; the next frame's
    flow is exact (the true depth).  With the depth fixed any weight on those pixels pulls the pose guess degrees
    off (rotation traded for translation); left out, the measured half alone gives the pose."""
    monkeypatch.setattr(observed, "GUESS_MIN_MEASURED", guess_min)
    monkeypatch.setattr(observed, "UNOBSERVED_WEIGHT", weight)
    m, ds, fe = build(frames=8)
    for f in ds:
        m.process(f, None)
    g = m.graph
    h, w = g.ba_shape
    a = g.n - 1
    true_disp = g.disps[a].clone()
    rel = se3_exp(torch.tensor([[0.3 / float(true_disp.mean()) / 4, 0.05, 0, 0, 0.03, 0.01]],
                               dtype=torch.float64))[0]  # a step sideways and a small turn
    pose_true = se3_mul(g.poses[a].double().cpu(), rel)
    R, t = edge_transforms(torch.stack([g.poses[a].double().cpu(), pose_true]), torch.tensor([0]), torch.tensor([1]))
    out = project_points(R.float(), t.float(), true_disp.reshape(1, -1), g.intrinsics, h, w)
    target = torch.stack([out["u"][0], out["v"][0]]).reshape(2, h, w)
    wrong = true_disp.clone()
    wrong[: h // 2] *= 3.0
    g.set_disps(torch.tensor([a]), wrong[None])
    measured = torch.ones(h, w, dtype=torch.bool)
    measured[: h // 2] = False
    m.state.observed.set(g.id_of(a), measured)
    track = TrackResult(is_keyframe=True, mean_flow=2.0, target=target, weight=torch.ones(2, h, w))
    pose = new_keyframe.pose_guess(m.state, a, track)
    err = se3_mul(se3_inv(pose_true[None]), pose[None])[0]
    rot_err = 2 * math.degrees(math.acos(min(1.0, abs(float(err[6])))))
    if off:
        assert rot_err > 1.0, rot_err  # measured 3.98 / 4.05 / 4.05 deg
    else:
        assert rot_err < 0.1, rot_err  # measured 0.025 (exact flow on the measured half; 4 iterations)


def test_the_window_ba_marks_the_pixels_its_edges_measure(monkeypatch):
    """A camera stepping sideways (2.5 / 1.25 BA px of parallax a keyframe): a new keyframe's columns nothing of
    the previous one lands on start as guesses, and the next window BA's edges measure them."""
    monkeypatch.setattr(observed, "UNOBSERVED_WEIGHT", 0.3)
    m, ds, fe = build(frames=16)
    at_add = []
    add = m._add_keyframe

    def recording_add(*args, **kw):
        kf_id = add(*args, **kw)
        if m.initialized:
            at_add.append(float(m.state.observed.masks[kf_id].float().mean()))
        return kf_id

    m._add_keyframe = recording_add
    for f in ds:
        m.process(f, None)
    assert at_add and max(at_add) < 1.0  # each new keyframe had guessed columns ...
    fracs = [float(m.state.observed.masks[i].float().mean()) for i in m.graph.ids.tolist()]
    assert min(fracs) == 1.0, fracs  # ... which the window BA's edges measured


@pytest.mark.parametrize("configured,live,expected", [(None, True, revisits.LIVE_THRESH), (None, False, 0.0),
                                                      (0.0, True, 0.0), (2.5, False, 2.5)])
def test_a_live_source_culls_its_revisits_unless_told_otherwise(configured, live, expected):
    """A live camera may drive the same places for hours: where the threshold is not set, its map culls revisit
    keyframes; a sequence of known length keeps every keyframe; a set threshold is kept either way."""
    pcfg = validate_pipeline({"graph": {"keyframes": {"revisit_thresh": configured}}})
    ds = fakes.FakeDataset(fakes.FakeDatasetConfig(frames=8, speed=SPEED))
    info = dataclasses.replace(ds.info(), num_frames=None) if live else ds.info()
    fe = fakes.ExactFrontend(fakes.ExactFrontendConfig(keyframe_every=2), ds=4)
    spec = get_registry().get("optimizer", "online_ba")
    m = Mapper(pcfg, info, fe, spec.factory(spec.config_model(), BuildContext(device=torch.device("cpu"))), None, "cpu")
    assert m.revisits.thresh == pytest.approx(expected * m.state.px_scale)
    assert (m.revisits.thresh > 0) == (expected > 0)
