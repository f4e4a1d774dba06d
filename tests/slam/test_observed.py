"""Measured and guessed depth pixels (pvslam_core/slam/observed.py): the masks, how a keyframe inherits them, how an
edge with parallax marks them (the mapper's use: tests/slam/test_mapper.py)."""
import pytest
import torch

from pvslam_core.geometry.lie import se3_exp
from pvslam_core.slam.observed import ObservedMasks

H, W = 12, 16
INTR = torch.tensor([20.0, 20.0, 7.5, 5.5])


def test_factor_is_one_where_measured_and_the_weight_elsewhere():
    obs = ObservedMasks(weight=0.2, parallax=1.0)
    m = torch.zeros(H, W, dtype=torch.bool)
    m[:, : W // 2] = True
    obs.set(7, m)
    f = obs.factor([7, 3], (H, W), "cpu")  # keyframe 3 has no mask on record: measured
    assert f.shape == (2, 1, H, W)
    assert torch.all(f[0, 0, :, : W // 2] == 1) and torch.allclose(f[0, 0, :, W // 2:], torch.tensor(0.2))
    assert torch.all(f[1] == 1)
    assert obs.active and not ObservedMasks(weight=1.0, parallax=1.0).active
    obs.forget(7)
    assert torch.all(obs.factor([7], (H, W), "cpu") == 1)


def _poses(*motions):
    """T_wc [n, 7]: the identity, then each twist (tx, ty, tz, rx, ry, rz) applied to it."""
    out = [torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64)]
    for xi in motions:
        out.append(se3_exp(torch.tensor([xi], dtype=torch.float64))[0])
    return torch.stack(out)


@pytest.mark.parametrize("motion, marked", [((0, 0, 0, 0, 0.1, 0), False),  # a turn on the spot: no parallax
                                            ((0.5, 0, 0, 0, 0, 0), True)])  # a step sideways: 20 * 0.5 * 0.25 px
def test_an_edge_marks_its_source_pixels_only_with_parallax(motion, marked):
    obs = ObservedMasks(weight=0.1, parallax=1.0)
    for kf_id in (10, 11):
        obs.set(kf_id, torch.zeros(H, W, dtype=torch.bool))
    disps = torch.full((2, H, W), 0.25)
    poses = _poses(motion)
    weight = torch.ones(1, 2, H, W)
    obs.mark(poses, disps, INTR, [10, 11], torch.tensor([0]), torch.tensor([1]), weight)
    assert bool(obs.masks[10].all()) is marked  # 2.5 px of parallax everywhere for the step
    assert not bool(obs.masks[11].any())  # the edge's target keyframe is not measured by it


def test_parallax_on_pixels_without_confidence_marks_nothing():
    obs = ObservedMasks(weight=0.1, parallax=1.0)
    obs.set(0, torch.zeros(H, W, dtype=torch.bool))
    disps = torch.full((2, H, W), 0.25)
    weight = torch.ones(1, 2, H, W)
    weight[..., : W // 2] = 0.0  # the left half's flow is not trusted
    obs.mark(_poses((0.5, 0, 0, 0, 0, 0)), disps, INTR, [0, 1], torch.tensor([0]), torch.tensor([1]), weight)
    assert not bool(obs.masks[0][:, : W // 2].any()) and bool(obs.masks[0][:, W // 2:].all())


def test_a_far_pixel_is_measured_by_a_baseline_that_measures_the_median_depth():
    """Most of the image near (inverse depth 0.25: 2.5 px for the step), the right columns 100x farther (0.025 px):
    the step measures that they are far, so they count as measured too (at the median's parallax)."""
    obs = ObservedMasks(weight=0.1, parallax=1.0)
    obs.set(0, torch.zeros(H, W, dtype=torch.bool))
    disps = torch.full((2, H, W), 0.25)
    disps[0, :, W // 2 + 2:] = 0.0025  # 6 of 16 columns: the median is a near pixel's
    weight = torch.ones(1, 2, H, W)
    obs.mark(_poses((0.5, 0, 0, 0, 0, 0)), disps, INTR, [0, 1], torch.tensor([0]), torch.tensor([1]), weight)
    assert bool(obs.masks[0].all())
    # a baseline too short for the median depth too: nothing (0.1 step: 0.5 px at the median)
    obs.set(0, torch.zeros(H, W, dtype=torch.bool))
    obs.mark(_poses((0.1, 0, 0, 0, 0, 0)), disps, INTR, [0, 1], torch.tensor([0]), torch.tensor([1]), weight)
    assert not bool(obs.masks[0].any())
