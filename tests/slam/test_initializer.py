"""Two-view initialisation (pvslam_core.slam.initializer) on exact correspondences."""
import torch

from pvslam_core.geometry.lie import se3_inv, se3_mul
from pvslam_core.geometry.projective import reproject
from pvslam_core.geometry.testing import make_problem
from pvslam_core.slam.initializer import two_view_init


def _pair(pr, a, b):
    coords, valid = reproject(pr.poses, pr.disps.double(), pr.intr.double(), torch.tensor([a]), torch.tensor([b]))
    return coords[0].permute(2, 0, 1).float(), valid[0].float().expand(2, -1, -1).clone()


def test_recovers_relative_pose_up_to_scale_and_depth():
    pr = make_problem(n=6, h=60, w=80, seed=1, step=0.25)
    target, weight = _pair(pr, 0, 5)
    init = two_view_init(target, weight, pr.intr, min_parallax_deg=0.5)
    assert init is not None and init.inliers > 1000
    true_rel = se3_mul(se3_inv(pr.poses[0]), pr.poses[5])  # camera 5 in camera 0
    est = init.pose_wc
    cos = torch.nn.functional.cosine_similarity(est[:3], true_rel[:3], dim=0)
    assert float(cos) > 0.999  # translation direction
    assert float((est[3:] - true_rel[3:]).abs().max()) < 2e-3 or float((est[3:] + true_rel[3:]).abs().max()) < 2e-3
    d = init.disp0
    assert abs(float(d.median()) - 1.0) < 1e-3  # the map scale: median inverse depth 1
    scale = float(est[:3].norm() / true_rel[:3].norm())  # map units per metre
    ok = weight[0] > 0
    rel_err = (d[ok] * scale - pr.disps[0][ok]).abs() / pr.disps[0][ok]
    assert float(rel_err.median()) < 0.01  # the same scale links depth and translation


def test_declines_without_parallax():
    pr = make_problem(n=2, h=60, w=80, seed=1, step=0.004)  # millimetres of motion
    target, weight = _pair(pr, 0, 1)
    assert two_view_init(target, weight, pr.intr, min_parallax_deg=0.5) is None
    assert two_view_init(target, torch.zeros_like(weight), pr.intr) is None  # nothing confident


def test_confidence_is_relative_to_the_pairs_own_weights():
    """With ``relative_weight``, weights all scaled below 0.5 (a frontend whose confidences carry a texture term)
    initialise as the unscaled ones do; only pixels well below the pair's own high weights are not confident."""
    pr = make_problem(n=6, h=60, w=80, seed=1, step=0.25)
    target, weight = _pair(pr, 0, 5)
    ref = two_view_init(target, weight, pr.intr, min_parallax_deg=0.5)
    assert two_view_init(target, weight * 0.3, pr.intr, min_parallax_deg=0.5) is None  # the absolute 0.5
    low = two_view_init(target, weight * 0.3, pr.intr, min_parallax_deg=0.5, relative_weight=True)
    assert ref is not None and low is not None and low.inliers == ref.inliers
    torch.testing.assert_close(low.pose_wc, ref.pose_wc)
    # where a third of the pixels are strong, the faint rest (a twentieth of their weight) is not confident
    mixed = weight * 0.05
    mixed[:, :20] = weight[:, :20]  # the top 20 of 60 rows
    part = two_view_init(target, mixed, pr.intr, min_parallax_deg=0.5, relative_weight=True)
    assert part is not None and part.inliers <= int((weight[0, :20] > 0).sum()) < ref.inliers


def test_relative_confidence_has_a_floor():
    """Where the flow failed almost everywhere (the pair's 90th-percentile weight ~0), the relative threshold does not
    fall to ~0 with it: faint weights are no correspondences, and the pair is declined as having none."""
    pr = make_problem(n=6, h=60, w=80, seed=1, step=0.25)
    target, weight = _pair(pr, 0, 5)
    faint = weight * 0.01  # a trace of weight everywhere: q90 = 0.01, half of it 0.005
    assert two_view_init(target, faint, pr.intr, min_parallax_deg=0.5, relative_weight=True) is None
    # the same correspondences at a weight just above the floor initialise
    assert two_view_init(target, weight * 0.12, pr.intr, min_parallax_deg=0.5, relative_weight=True) is not None


def test_the_parallax_gate_reads_the_requested_quantile():
    """``parallax_quantile``: the pair passes when that quantile of its points' parallax reaches the threshold.  A
    threshold between the pair's median and its 75th-percentile parallax declines it at 0.5 (saying so) and accepts
    it at 0.75 with the same motion; the reported parallax is the quantile's."""
    from pvslam_core.slam.initializer import TwoViewOptions, two_view_init_why

    pr = make_problem(n=6, h=60, w=80, seed=1, step=0.25)
    target, weight = _pair(pr, 0, 5)
    at = {q: two_view_init_why(target, weight, pr.intr,
                               TwoViewOptions(min_parallax_deg=0.01, parallax_quantile=q))[0]
          for q in (0.5, 0.75)}
    med, q75 = at[0.5].parallax_deg, at[0.75].parallax_deg
    assert q75 > 1.05 * med  # the scene's depths differ: the quantiles differ
    thr = (med + q75) / 2
    no, why = two_view_init_why(target, weight, pr.intr, TwoViewOptions(min_parallax_deg=thr))
    assert no is None and why.startswith("median parallax")
    yes, why = two_view_init_why(target, weight, pr.intr,
                                 TwoViewOptions(min_parallax_deg=thr, parallax_quantile=0.75))
    assert yes is not None and why == "" and yes.parallax_deg == q75
    torch.testing.assert_close(yes.pose_wc, at[0.5].pose_wc)
