"""Two-view initialisation on dense, BA-resolution correspondences with little parallax:
the motion is chosen by cheirality and the Sampson cost of multi-start refined hypotheses, not by the H/E score
ratio (which sits near 0.5 whenever dense, accurate flow fits both models).

The synthetic pairs are exact projections (plus Gaussian noise) of a known scene, so the reference is the true
motion: the rotation and the direction of the translation."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from pvslam_core.geometry.lie import se3_to_matrix
from pvslam_core.slam.initializer import TwoViewOptions, refine_relative_pose, sampson_error, two_view_init_why

H, W = 30, 40
FX = FY = 35.0
CX, CY = 19.5, 14.5
K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])
INTR = torch.tensor([FX, FY, CX, CY])


def _rot(axis, deg):
    a = np.asarray(axis, float)
    return cv2.Rodrigues(a / np.linalg.norm(a) * np.radians(deg))[0]


def _scene(kind: str) -> np.ndarray:
    """``[H*W, 3]`` points (view 0) seen by each BA pixel."""
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    rx, ry = (xs - CX) / FX, (ys - CY) / FY
    if kind == "plane":  # a slanted wall
        z = 3.0 / (0.2 * rx - 0.1 * ry + 1.0)
    else:  # a wall with two boxes in front of it
        z = np.full_like(rx, 3.0)
        z[5:15, 5:15] = 1.5
        z[18:28, 25:38] = 2.2
    return np.stack([rx * z, ry * z, z], -1).reshape(-1, 3)


def _pair(kind: str, parallax_deg: float, rot_deg: float, noise: float, seed: int = 0):
    """Dense target of view 0's pixels in view 1 ``[2, H, W]`` (BA px), weights, true ``R``, unit ``t`` (view 0 ->
    view 1: ``X1 = R X0 + t``)."""
    rng = np.random.default_rng(seed)
    X = _scene(kind)
    R = _rot((0.3, 1.0, 0.1), rot_deg)
    t = np.array([1.0, 0.0, 0.2])
    t = t / np.linalg.norm(t) * np.radians(parallax_deg) * np.median(X[:, 2])
    q = (X @ R.T + t) @ K.T
    uv = q[:, :2] / q[:, 2:] + rng.normal(0.0, noise, (len(X), 2))
    target = torch.from_numpy(uv.T.reshape(2, H, W)).float()
    return target, torch.ones(2, H, W), R, t / max(np.linalg.norm(t), 1e-12)


def _errors(init, R, t):
    """(rotation error, translation direction error) in degrees of an initialisation against the truth."""
    T_c1c0 = np.linalg.inv(se3_to_matrix(init.pose_wc).numpy())
    Re, te = T_c1c0[:3, :3], T_c1c0[:3, 3]
    rerr = np.degrees(np.arccos(np.clip((np.trace(Re.T @ R) - 1) / 2, -1, 1)))
    terr = np.degrees(np.arccos(np.clip(te @ t / np.linalg.norm(te), -1, 1)))
    return rerr, terr


@pytest.mark.parametrize("tie", [None, 1.25])  # the tie check (tie_ratio) leaves a clear pair alone
@pytest.mark.parametrize("rot_deg", [2.0, 10.0])
@pytest.mark.parametrize("parallax_deg", [1.0, 2.0])
def test_scene_with_depth_gets_the_true_translation(parallax_deg, rot_deg, tie):
    target, weight, R, t = _pair("boxes", parallax_deg, rot_deg, noise=0.05)
    init, why = two_view_init_why(target, weight, INTR, TwoViewOptions(min_parallax_deg=0.5, tie_ratio=tie))
    assert init is not None, why
    rerr, terr = _errors(init, R, t)
    assert init.model == "E"
    assert terr < 3.0 and rerr < 0.2, (terr, rerr)


def test_without_refinement_the_same_pairs_go_wrong():
    """Without the refinement (hypotheses: RANSAC's minimal-sample essential matrix and the homography's
    decompositions only) the same pairs go wrong: the test above checks something."""
    errs = []
    for par in (1.0, 2.0):
        for rot in (2.0, 10.0):
            target, weight, R, t = _pair("boxes", par, rot, noise=0.05)
            opts = TwoViewOptions(min_parallax_deg=0.5, refine=False)
            init, _ = two_view_init_why(target, weight, INTR, opts)
            errs.append(_errors(init, R, t)[1] if init is not None else 180.0)
    assert max(errs) > 10.0


@pytest.mark.parametrize("tie", [None, 1.25])
@pytest.mark.parametrize("parallax_deg", [2.0, 4.0])
def test_planar_scene_keeps_the_homography_solution(parallax_deg, tie):
    # a plane leaves the essential matrix a family of solutions; the homography's decomposition is the answer
    target, weight, R, t = _pair("plane", parallax_deg, 10.0, noise=0.05)
    init, why = two_view_init_why(target, weight, INTR, TwoViewOptions(min_parallax_deg=0.5, tie_ratio=tie))
    assert init is not None, why
    rerr, terr = _errors(init, R, t)
    assert terr < 3.0 and rerr < 0.2, (terr, rerr)


def test_pure_rotation_is_declined():
    target, weight, _, _ = _pair("boxes", 0.0, 8.0, noise=0.05)
    init, why = two_view_init_why(target, weight, INTR, TwoViewOptions(min_parallax_deg=0.5))
    assert init is None and "parallax" in why


def test_refinement_finds_the_true_motion_from_a_wrong_start():
    X = _scene("boxes")
    R = _rot((0.3, 1.0, 0.1), 5.0)
    t = np.array([0.0, 1.0, 0.3])
    t = t / np.linalg.norm(t)
    X1 = X @ R.T + 0.05 * t
    x0 = X / X[:, 2:]
    x1 = X1 / X1[:, 2:]
    # start: the right rotation, a translation 90 deg off
    minima = refine_relative_pose(x0, x1, [(R, np.array([1.0, 0.0, 0.0]))], f_scale=0.3 / FX)
    assert [m[2] for m in minima] == sorted(m[2] for m in minima)  # lowest cost first
    Rr, tr, cost = minima[0]
    ang = np.degrees(np.arccos(min(1.0, abs(float(tr.ravel() @ t)))))  # up to sign (the cheirality test's job)
    assert ang < 0.5 and np.allclose(Rr, R, atol=1e-4)
    # the Sampson distance of the true motion is zero on exact data; of the wrong start, not
    E_true = np.cross(np.eye(3), t) @ R  # [t]x R (row i of [t]x is e_i x t)
    E_start = np.cross(np.eye(3), np.array([1.0, 0.0, 0.0])) @ R
    assert np.abs(sampson_error(E_true, x0, x1)).max() < 1e-9
    assert np.abs(sampson_error(E_start, x0, x1)).max() * FX > 0.5


def test_an_ambiguous_pair_is_declined_not_started_wrong():
    """A recorded pair (busy_street seed 86, keyframes of frames 0 and 9 of the flow frontend, chain-checked: 111
    confident correspondences, 0.7 BA px of median flow, all of them on the true motion). The true forward motion
    has 72 of them in front (noise behind the focus of expansion), under the 65 % bar of the 111 of a sideways motion
    that fits 11x worse; chosen, that motion started the map 89 deg off. With ``ambiguity_ratio`` the pair is
    declined (and the next one, with more motion, tried)."""
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / "init_pair_busy_street_86.npz")
    target, weight, intr = (torch.from_numpy(d[k]) for k in ("target", "weight", "intr"))
    kw = dict(min_parallax_deg=0.5, relative_weight=True, parallax_quantile=0.75)
    init, why = two_view_init_why(target, weight, intr, TwoViewOptions(**kw))
    assert init is not None and why == ""
    T_m_a = np.linalg.inv(se3_to_matrix(init.pose_wc).numpy())  # view 0 -> view 1
    t_est, t_true = T_m_a[:3, 3], d["T_m_a"][:3, 3]
    cos = float(t_est @ t_true / np.linalg.norm(t_est) / np.linalg.norm(t_true))
    assert abs(cos) < 0.2  # started wrong: the translation about 90 deg off
    init, why = two_view_init_why(target, weight, intr, TwoViewOptions(ambiguity_ratio=3.0, **kw))
    assert init is None and why.startswith("ambiguous") and "72 of 111" in why, why


def test_a_pair_that_cannot_tell_two_motions_apart_is_declined():
    """driving_loop/102, keyframes 0 and 4 (frames 0 and 8), with the chain check's
    weights as the bootstrap passed them: the forward drive puts 109 points in front at a truncated Sampson cost of
    0.0011 px^2, a motion 50 deg to the side 110 at 0.0010; chosen, it started the map 55 deg off.  With
    ``tie_ratio`` the pair is declined (the bootstrap's next pair, 2-4, then fits the forward drive 100x better)."""
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / "init_pair_driving_loop_102.npz")
    target, weight, intr = (torch.from_numpy(d[k]) for k in ("target", "weight", "intr"))
    kw = dict(min_parallax_deg=0.5, relative_weight=True, parallax_quantile=0.75, ambiguity_ratio=3.0)
    t_true = d["T_m_a"][:3, 3]

    def heading_error(init):
        t_est = np.linalg.inv(se3_to_matrix(init.pose_wc).numpy())[:3, 3]
        return float(np.degrees(np.arccos(t_est @ t_true / np.linalg.norm(t_est) / np.linalg.norm(t_true))))

    init, why = two_view_init_why(target, weight, intr, TwoViewOptions(**kw))
    assert init is not None and heading_error(init) > 40  # started wrong (55 deg)
    init, why = two_view_init_why(target, weight, intr, TwoViewOptions(tie_ratio=1.25, **kw))
    assert init is None and why.startswith("ambiguous: two motions"), why
    # a tighter tie: the 10 % apart pass
    init, why = two_view_init_why(target, weight, intr, TwoViewOptions(tie_ratio=1.05, **kw))
    assert init is not None and heading_error(init) > 40
