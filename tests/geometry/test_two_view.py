"""find_essential: OpenCV's RANSAC essential matrix with one behaviour on every OpenCV version (5.1 raises on
degenerate data), and its callers' handling of "no essential matrix"."""
import cv2
import numpy as np
import pytest
import torch

from pvslam_core.geometry.two_view import find_essential

K = np.array([[50.0, 0.0, 20.0], [0.0, 50.0, 15.0], [0.0, 0.0, 1.0]])


def _views(t, yaw=0.05, n=200, seed=0):
    """Pixels ``[n, 2]`` of random points 3-10 m ahead in two views (``X_1 = R X_0 + t``)."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(3, 10, n)]
    R = cv2.Rodrigues(np.array([0.0, yaw, 0.0]))[0]
    X1 = X @ R.T + np.asarray(t, float)
    proj = lambda P: (P[:, :2] / P[:, 2:]) * 50.0 + [20.0, 15.0]  # noqa: E731
    return proj(X), proj(X1), R


def _raise(*a, **k):
    raise cv2.error("OpenCV(5.1.0) mathfuncs.cpp:1601: error: (-215:Assertion failed) in function 'solvePoly'")


def test_fits_a_known_motion():
    p0, p1, R = _views([0.3, 0.0, 1.0])
    E, mask = find_essential(p0, p1, K, 0.5)
    assert E is not None and E.shape == (3, 3) and int(mask.sum()) > 190
    x0 = np.c_[p0, np.ones(len(p0))] @ np.linalg.inv(K).T
    x1 = np.c_[p1, np.ones(len(p1))] @ np.linalg.inv(K).T
    assert np.abs(np.einsum("ni,ij,nj->n", x1, E, x0)).max() < 1e-6  # the epipolar constraint holds


@pytest.mark.parametrize("case", ["identical", "rotation"])
def test_degenerate_data_never_raises(case):
    # OpenCV 5.1 raises on these in findEssentialMat; 5.0 returns a matrix: either way no exception here
    p0, p1, _ = _views([0.0, 0.0, 0.0], yaw=0.0 if case == "identical" else 0.05)
    E, mask = find_essential(p0, p1, K, 0.5)
    assert (E is None) == (mask is None)


def test_an_opencv_error_means_no_essential_matrix(monkeypatch):
    p0, p1, _ = _views([0.3, 0.0, 1.0])
    monkeypatch.setattr(cv2, "findEssentialMat", _raise)
    assert find_essential(p0, p1, K, 0.5) == (None, None)


def test_callers_decline_instead_of_raising(monkeypatch):
    """Where OpenCV fails, the initialiser declines the pair and loop verification rejects the loop (they used to
    propagate the cv2.error: a run on OpenCV 5.1 ended at a turn on the spot)."""
    from pvslam_core.geometry.projective import reproject
    from pvslam_core.geometry.testing import make_problem
    from pvslam_core.slam.initializer import two_view_init
    from pvslam_plugins.loops.verification import OrbFeatures, verify

    pr = make_problem(n=6, h=60, w=80, seed=1, step=0.25)
    coords, valid = reproject(pr.poses, pr.disps.double(), pr.intr.double(), torch.tensor([0]), torch.tensor([5]))
    target = coords[0].permute(2, 0, 1).float()
    weight = valid[0].float().expand(2, -1, -1).clone()
    assert two_view_init(target, weight, pr.intr, min_parallax_deg=0.5) is not None  # fits without the failure
    monkeypatch.setattr(cv2, "findEssentialMat", _raise)
    assert two_view_init(target, weight, pr.intr, min_parallax_deg=0.5) is None
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.5, 0.5, (80, 2)).astype(np.float32)  # normalised coordinates
    desc = rng.integers(0, 256, (80, 32), dtype=np.uint8)
    a = OrbFeatures(points=pts, descriptors=desc, focal=200.0)
    res = verify(a, a, min_inliers=10, min_inlier_ratio=0.3)  # the same view twice: 80 matches, no fit
    assert res.matches == 80 and not res.accepted and "RANSAC failed" in res.message
