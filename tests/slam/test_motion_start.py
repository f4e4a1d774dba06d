"""The second start of a new keyframe's window BA after a stretch without parallax (pvslam_core/slam/motion_start.py):
the constant-velocity centre, and the window BA keeping the start whose result fits the flow better."""
import pytest
import torch

import fakes
from pvslam_core.config import validate_pipeline
from pvslam_core.interfaces import BuildContext
from pvslam_core.registry import get_registry
from pvslam_core.slam import loops, motion_start, window_ba
from pvslam_core.slam.graph import FrameGraph
from pvslam_core.slam.mapper import Mapper
from pvslam_core.slam.motion_start import constant_velocity_centre
from pvslam_core.types import OptimizerReport


def _graph(times, centres):
    g = FrameGraph(4, 4, torch.tensor([4.0, 4.0, 2.0, 2.0]))
    for n, (t, c) in enumerate(zip(times, centres)):
        pose = torch.tensor([*c, 0, 0, 0, 1.0])
        g.add_keyframe(n, t, pose, torch.ones(4, 4))
    return g


def _measured(fracs):
    return lambda kf_id: fracs[kf_id]


def test_the_centre_continues_the_last_measured_motion():
    """Keyframes at 0, 0.1, ..., 0.5 s moving 1 m/s along x, then two pan keyframes whose centres came out short
    (unmeasured) and the new one at 0.8 s: predicted from the measured pair (0.5 s, and the newest >= 0.25 s before
    it, 0.2 s), not from the pan keyframes."""
    times = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8]
    centres = [(t, 0.0, 0.0) for t in times[:6]] + [(0.52, 0.1, 0.0), (0.53, 0.2, 0.0), (0.55, 0.3, 0.0)]
    g = _graph(times, centres)
    fracs = {i: 0.9 for i in range(6)} | {6: 0.2, 7: 0.1, 8: 0.0}
    c = constant_velocity_centre(g, 8, _measured(fracs), 0.5, span=0.25, horizon=1.0)
    assert torch.allclose(c, torch.tensor([0.8, 0.0, 0.0], dtype=torch.float64), atol=1e-6), c
    # the span picks the pair: with 0.35 s it is (0.1, 0.5) s, the same line
    c = constant_velocity_centre(g, 8, _measured(fracs), 0.5, span=0.35, horizon=1.0)
    assert torch.allclose(c, torch.tensor([0.8, 0.0, 0.0], dtype=torch.float64), atol=1e-6), c


@pytest.mark.parametrize("case", ["reference measured", "one under, not a stretch", "past the horizon", "no pair",
                                  "before the fragment"])
def test_no_centre_where_there_is_nothing_to_continue(case):
    times = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    g = _graph(times, [(t, 0.0, 0.0) for t in times])
    fracs = {0: 0.9, 1: 0.9, 2: 0.9, 3: 0.9, 4: 0.1, 5: 0.1, 6: 0.0}
    kw = dict(span=0.25, horizon=1.0)
    if case == "reference measured":
        fracs[5] = 0.6
    elif case == "one under, not a stretch":  # a drive's newest keyframe is often under half measured
        fracs[4] = 0.6
    elif case == "past the horizon":
        kw["horizon"] = 0.2  # the last measured keyframe (0.3 s) is 0.3 s before the new one
    elif case == "no pair":
        fracs.update({0: 0.1, 1: 0.1})  # only 0.2 and 0.3 s are measured, 0.1 s apart
    else:
        kw["first"] = 2  # a new fragment from keyframe 2: its measured keyframes are 0.1 s apart
    assert constant_velocity_centre(g, 6, _measured(fracs), 0.5, **kw) is None


class _Still:
    """An optimizer that leaves the graph as it is: each start's result is the start itself."""

    def step(self, graph, obs):
        return OptimizerReport(num_edges=int(obs.ii.numel()))


def _mapper_after_a_pan(monkeypatch):
    """A mapper after 16 frames of the exact fake (sideways camera, constant speed, keyframe every 2nd frame), the
    two keyframes before its newest marked unmeasured (as after a pan), the optimizer replaced by :class:`_Still`."""
    monkeypatch.setattr(motion_start, "SPAN", 0.35)
    monkeypatch.setattr(loops, "NMS_KEYFRAMES", 0)
    pcfg = validate_pipeline({"graph": {"init": {"warmup": 3}, "ba_downsample": 4,
                                        "keyframes": {"redundant_thresh": 0.0}}})
    ds = fakes.FakeDataset(fakes.FakeDatasetConfig(frames=16, speed=0.4))
    fe = fakes.ExactFrontend(fakes.ExactFrontendConfig(keyframe_every=2), ds=4)
    spec = get_registry().get("optimizer", "online_ba")
    opt = spec.factory(spec.config_model(), BuildContext(device=torch.device("cpu")))
    m = Mapper(pcfg, ds.info(), fe, opt, None, "cpu")
    for f in ds:
        m.process(f, None)
    g = m.graph
    k = g.n - 1
    h, w = g.ba_shape
    for n in (1, 2):
        m.state.observed.set(g.id_of(k - n), torch.zeros(h, w, dtype=torch.bool))
    m.window_ba.optimizer = _Still()
    return m, k


def test_the_constant_velocity_start_wins_where_the_guess_is_off(monkeypatch):
    m, k = _mapper_after_a_pan(monkeypatch)
    g = m.graph
    expected = constant_velocity_centre(g, k, m.state.observed.fraction, 0.5, 0.35, 1.0)
    true = g.poses[k, :3].double().clone()
    assert float((expected - true).norm()) < 0.02 * float((g.poses[k, :3] - g.poses[k - 1, :3]).norm())
    g.poses[k, 0] += 0.5 * float((g.poses[k, :3] - g.poses[k - 1, :3]).norm())  # the guess half a step off
    age0 = g.edge_age.clone()
    asked = []
    observe = m.frontend.observe
    m.frontend.observe = lambda graph, ii, jj: asked.append(1) or observe(graph, ii, jj)
    m.window_ba.optimize_new(k, 2)
    assert len(asked) == 2  # once per round: the second start reuses the observations
    assert (m.window_ba.second_starts, m.window_ba.second_starts_kept) == (1, 1)
    assert torch.allclose(g.poses[k, :3].double(), expected.to(g.poses), atol=1e-5)
    window = m.cfg.edges.active_window
    touched = (g.ii >= k - window + 1) | (g.jj >= k - window + 1)
    assert bool((g.edge_age[touched] - age0[: g.num_edges][touched] == 2).all())  # aged by the rounds, once


def test_the_guess_stays_where_the_prediction_is_worse(monkeypatch):
    """A camera that did stop (a stop-and-spin): the prediction is off, the guess right; the guess's result stays."""
    m, k = _mapper_after_a_pan(monkeypatch)
    g = m.graph
    before = g.poses.clone()
    step = float((g.poses[k, :3] - g.poses[k - 1, :3]).norm())
    wrong = g.poses[k, :3].double() + torch.tensor([0.0, 0.5 * step, 0.0], dtype=torch.float64)
    monkeypatch.setattr(motion_start, "constant_velocity_centre", lambda *a, **kw: wrong)
    m.window_ba.optimize_new(k, 1)
    assert (m.window_ba.second_starts, m.window_ba.second_starts_kept) == (1, 0)
    assert torch.equal(g.poses, before)


def test_switched_off_it_runs_one_window_ba(monkeypatch):
    m, k = _mapper_after_a_pan(monkeypatch)
    monkeypatch.setattr(window_ba, "SECOND_START", False)
    calls = []
    m.window_ba.optimizer = type("Counting", (_Still,),
                                 {"step": lambda self, g, o: calls.append(1) or OptimizerReport()})()
    m.window_ba.optimize_new(k, 2)
    assert len(calls) == 2 and (m.window_ba.second_starts, m.window_ba.second_starts_kept) == (0, 0)
