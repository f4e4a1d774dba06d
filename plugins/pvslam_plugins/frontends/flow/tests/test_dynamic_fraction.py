"""The edge guard ``dynamic.max_fraction``: an edge whose dynamic mask would cover more than that share of its pixels
gets no mask (the estimate, not the scene, is taken to be off).  At 0.5 a vehicle filling most of a narrow view lost
its mask exactly when it mattered (docs/decisions.md: frontend.dynamic.max_fraction).  The residual test is a stub
here: the reprojection is the identity, so the residual is the target's own shift."""
import pytest
import torch

from pvslam_plugins.frontends.flow import dynamic_masking as masking_module
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
import _flow_scenes as S

H, W = 12, 16


@pytest.fixture
def masking(monkeypatch):
    """A masking of two keyframes without segments, configured by ``cfg``."""
    # the relative threshold is off: with it no more than half the valid pixels can be candidates at all, and the
    # guard acts on what regions, their growth and segment votes add
    monkeypatch.setattr(masking_module, "DYNAMIC_REL_THRESH", 0.0)

    def make(**cfg):
        reproject, coords = S.identity_reproject(H, W)
        return S.masking(H, W, {0: (None, []), 1: (None, [])}, reproject, **cfg), coords

    return make


def _judge(m, coords, cols: int):
    """One edge 0 -> 1 whose left ``cols`` columns moved 3 BA px (the rest static), observed twice (its mask is judged
    from the second observation on); returns the edge's mask."""
    du = torch.zeros(H, W, dtype=torch.float64)
    du[:, :cols] = 3.0
    target = S.shifted_target(coords, du).float()
    m.edge_added((0, 1), target)
    g = S.TwoKeyframeGraph(H, W)
    for _ in range(2):
        m.observe(g, torch.tensor([0]), torch.tensor([1]), [(0, 1)], target[None], torch.ones(1, H, W))
    return m.edge_mask((0, 1))


def test_a_mover_over_most_of_the_view_keeps_its_mask(masking):
    m, coords = masking()
    assert FlowFrontendConfig().dynamic.max_fraction == pytest.approx(0.8)
    dyn = _judge(m, coords, 10)  # 10 of 16 columns (+1 of growth: 69 %)
    assert dyn is not None
    assert bool((dyn[:, :10] > 0).all()) and not bool((dyn[:, 12:] > 0).any())
    kf = m.keyframe(0)
    assert kf.dyn is not None and bool((kf.dyn[:, :10] > 0).all())  # the keyframe's vote follows


def test_an_edge_that_is_almost_all_dynamic_gets_no_mask(masking):
    m, coords = masking()
    assert _judge(m, coords, 14) is None  # 15 / 16 of the pixels: the estimate is off, not the scene


@pytest.mark.parametrize("guard, kept", [(0.5, False), (0.8, True)])
def test_the_guard_is_the_config_value(masking, guard, kept):
    m, coords = masking(max_fraction=guard)
    assert (_judge(m, coords, 10) is not None) == kept
