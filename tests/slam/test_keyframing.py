"""Which keyframes stay (pvslam_core.slam.flow_distance and the keyframe policy's redundancy test): the distance
combines the mean and the 90th percentile of the induced flow, checked against a pinhole projection written here; a
keyframe after a long gap is never redundant."""
import numpy as np
import torch

import fakes
from pvslam_core.adapt import REF_BA_FOCAL
from pvslam_core.config import validate_pipeline
from pvslam_core.geometry.projective import frame_distance
from pvslam_core.interfaces import BuildContext
from pvslam_core.registry import get_registry
from pvslam_core.slam import keyframes
from pvslam_core.slam.flow_distance import keyframe_distance
from pvslam_core.slam.mapper import Mapper

H, W, FX, CX, CY = 12, 16, 10.0, 7.5, 5.5


def _brute_flow(disp: np.ndarray, t: np.ndarray) -> np.ndarray:
    """|flow| of every pixel for a camera translated by ``t`` (no rotation: full = translation-only flow)."""
    out = np.zeros((H, W))
    for y in range(H):
        for x in range(W):
            p = np.array([(x - CX) / FX, (y - CY) / FX, 1.0]) / disp[y, x] - t
            out[y, x] = np.hypot(FX * p[0] / p[2] + CX - x, FX * p[1] / p[2] + CY - y)
    return out


def test_distance_is_the_mean_or_the_high_quantile_of_the_induced_flow():
    disp = np.full((H, W), 0.02)  # a far scene ...
    disp[10:] = 1.0  # ... with a near strip at the bottom (a sixth of the image): the road
    t = np.array([0.0, 0.0, 0.1])  # forward motion
    poses = torch.tensor([[0, 0, 0, 0, 0, 0, 1.0], [*t, 0, 0, 0, 1.0]], dtype=torch.float64)
    intr = torch.tensor([FX, FX, CX, CY])
    d = torch.tensor(disp, dtype=torch.float64)
    flow = _brute_flow(disp, t)
    mean, q90 = flow.mean(), float(torch.quantile(torch.tensor(flow.ravel()), 0.9))
    assert q90 > 2.5 * mean  # the mean alone would call these keyframes close
    got = keyframe_distance(poses, d, intr, thresh=1.5, max_flow=4.0)
    assert abs(got - max(mean, q90 * 1.5 / 4.0)) < 1e-6  # (the quantile is taken in float32)
    plain = keyframe_distance(poses, d, intr, thresh=1.5, max_flow=0.0)
    assert abs(plain - mean) < 1e-9
    fd = frame_distance(poses, d[None], intr, torch.tensor([0]), torch.tensor([0 + 1]).clamp(max=1))
    assert abs(float(fd[0]) - plain) < 1e-9  # the DROID frame distance when the quantile is off
    # the camera passes most of the near points: too few valid pixels -> "far", never redundant
    assert keyframe_distance(torch.tensor([[0, 0, 0, 0, 0, 0, 1.0], [0, 0, 5.0, 0, 0, 0, 1.0]],
                                          dtype=torch.float64), torch.ones(H, W, dtype=torch.float64), intr,
                             1.5, 4.0) == 1000.0


def _kept_gaps(max_gap_s):
    """The fake plugins of the framework tests (exact targets), every keyframe "close" by distance."""
    pcfg = validate_pipeline({"graph": {"init": {"warmup": 3}, "ba_downsample": 4,
                                        "keyframes": {"redundant_thresh": 1e6, "max_gap_s": max_gap_s}}})
    ds = fakes.FakeDataset(fakes.FakeDatasetConfig(frames=40, speed=0.4))
    fe = fakes.ExactFrontend(fakes.ExactFrontendConfig(keyframe_every=2), ds=4)
    spec = get_registry().get("optimizer", "online_ba")
    m = Mapper(pcfg, ds.info(), fe, spec.factory(spec.config_model(), BuildContext(device=torch.device("cpu"))),
               None, "cpu")
    for f in ds:
        m.process(f, None)
    ts = m.graph.timestamps.tolist()
    return m, np.diff(ts)


def test_a_keyframe_after_a_long_gap_is_never_redundant(monkeypatch):
    # the quantile gate at 4 BA px of the fake camera (f = 10 BA px at 1/4; the constant is in reference BA px)
    monkeypatch.setattr(keyframes, "REDUNDANT_MAX_FLOW", 4.0 * REF_BA_FOCAL / (fakes.F / 4))
    m_cap, gaps_cap = _kept_gaps(max_gap_s=0.25)
    m_free, gaps_free = _kept_gaps(max_gap_s=100.0)
    assert gaps_free.max() > 0.6  # by distance alone, keyframes are far apart (until the views stop overlapping)
    # keyframes are proposed every 0.2 s (every 2nd frame): none is removed when that would leave more than 0.25 s
    assert gaps_cap.max() <= 0.25 + 1e-9 and m_cap.graph.n > m_free.graph.n
    for m in (m_cap, m_free):
        m.finalize()
        assert torch.isfinite(m.trajectory()[1]).all()
