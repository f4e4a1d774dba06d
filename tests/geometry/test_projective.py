import torch

from pvslam_core.geometry.lie import se3_exp, se3_mul, identity_se3
from pvslam_core.geometry.projective import depth_to_points, frame_distance, pixel_grid, reproject


def _setup(dtype=torch.float64, N=3, h=5, w=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    poses = se3_exp(0.1 * torch.randn(N, 6, generator=g, dtype=torch.float64))
    disps = (0.2 + 0.5 * torch.rand(N, h, w, generator=g, dtype=torch.float64)).to(dtype)
    intr = torch.tensor([8.0, 9.0, (w - 1) / 2, (h - 1) / 2], dtype=dtype)
    return poses, disps, intr


def test_pixel_grid():
    g = pixel_grid(3, 4, "cpu", torch.float32)
    assert g.shape == (3, 4, 2)
    assert g[2, 3].tolist() == [3.0, 2.0] and g[0, 1].tolist() == [1.0, 0.0]


def test_identity_reprojection_and_roundtrip():
    poses, disps, intr = _setup()
    coords, valid = reproject(poses, disps, intr, torch.tensor([0, 1]), torch.tensor([0, 1]))
    assert valid.all()
    assert torch.allclose(coords, pixel_grid(5, 7, "cpu", torch.float64).expand(2, 5, 7, 2), atol=1e-12)
    # i -> j -> back to i with j's depth equal to the transformed point depth
    pts = depth_to_points(disps[0], intr)
    assert torch.allclose(pts[..., 2], 1 / disps[0])


def test_jacobians_against_autograd():
    poses, disps, intr = _setup()
    ii, jj = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 0])
    coords, valid, Ji, Jj, Jd = reproject(poses, disps, intr, ii, jj, jacobians=True)
    assert valid.all()

    def f(xi_i, xi_j, dd):
        # convention: T_wc <- T_wc Exp(-xi)  (left retraction of world-to-camera poses)
        P = torch.cat([se3_mul(poses[ii], se3_exp(-xi_i)), se3_mul(poses[jj], se3_exp(-xi_j))])
        D = torch.cat([disps[ii] + dd, disps[jj]])
        return reproject(P, D, intr, torch.arange(3), torch.arange(3) + 3)[0]

    z6 = torch.zeros(3, 6, dtype=torch.float64)
    J = torch.autograd.functional.jacobian(f, (z6, z6, torch.zeros_like(disps)))
    E = torch.arange(3)
    Jia = J[0][E, :, :, :, E]  # [3, h, w, 2, 6]
    Jja = J[1][E, :, :, :, E]
    Jda = torch.einsum("ehwcehw->ehwc", J[2])
    assert torch.allclose(Ji, Jia, atol=1e-10)
    assert torch.allclose(Jj, Jja, atol=1e-10)
    assert torch.allclose(Jd, Jda, atol=1e-10)


def test_valid_mask_behind_camera():
    h, w = 4, 4
    intr = torch.tensor([4.0, 4.0, 1.5, 1.5], dtype=torch.float64)
    disps = torch.full((2, h, w), 0.5, dtype=torch.float64)  # depth 2
    poses = torch.stack([identity_se3((), torch.float64), identity_se3((), torch.float64)])
    poses[1, 2] = 3.0  # camera 1 is 3 m ahead: points are behind it
    _, valid = reproject(poses, disps, intr, torch.tensor([0]), torch.tensor([1]))
    assert not valid.any()


def test_frame_distance():
    poses, disps, intr = _setup(dtype=torch.float32)
    ii, jj = torch.tensor([0, 1, 0]), torch.tensor([0, 2, 2])
    d = frame_distance(poses, disps, intr, ii, jj)
    assert d[0] == 0 and (d[1:] > 0).all()
    # pure translation: beta does not matter; the flow is the same for both terms
    P = torch.stack([identity_se3((), torch.float64)] * 2)
    P[1, 0] = 0.1
    D = torch.full((2, 5, 7), 0.5)
    d1 = frame_distance(P, D, intr, torch.tensor([0]), torch.tensor([1]), beta=0.0)
    d2 = frame_distance(P, D, intr, torch.tensor([0]), torch.tensor([1]), beta=1.0)
    assert torch.allclose(d1, d2) and torch.allclose(d1, torch.tensor([0.1 * 0.5 * 8.0]))
    # subsampled grid gives a close value
    ds = frame_distance(poses, disps, intr, ii, jj, stride=2)
    assert torch.allclose(ds[1:], d[1:], rtol=0.3)
    # camera far ahead: nothing valid -> 1000
    P[1, 2] = 10.0
    assert frame_distance(P, D, intr, torch.tensor([0]), torch.tensor([1]))[0] == 1000.0


def test_reprojection_matches_opencv_projectpoints():
    """An independent check of ``reproject`` (the BA tests build their targets with it): back-project keyframe i's
    pixels with its depth, then project them into keyframe j with OpenCV's ``projectPoints`` (world-to-camera
    rotation vector and translation of camera j) and compare."""
    import cv2
    import numpy as np

    from pvslam_core.geometry.lie import quat_to_rotmat

    poses, disps, intr = _setup(h=6, w=9)
    i, j = 0, 2
    coords, valid = reproject(poses, disps, intr, torch.tensor([i]), torch.tensor([j]))
    fx, fy, cx, cy = intr.tolist()
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    g = pixel_grid(6, 9, "cpu", torch.float64)
    z = 1.0 / disps[i]
    Xc = torch.stack([(g[..., 0] - cx) / fx * z, (g[..., 1] - cy) / fy * z, z], -1).reshape(-1, 3).numpy()
    R_i, t_i = quat_to_rotmat(poses[i, 3:]).numpy(), poses[i, :3].numpy()  # camera i -> world (T_wc)
    Xw = Xc @ R_i.T + t_i
    R_j, t_j = quat_to_rotmat(poses[j, 3:]).numpy(), poses[j, :3].numpy()
    R_cw, t_cw = R_j.T, -R_j.T @ t_j  # world -> camera j
    uv, _ = cv2.projectPoints(Xw, cv2.Rodrigues(R_cw)[0], t_cw, K, None)
    ok = valid[0].reshape(-1).numpy()
    assert ok.mean() > 0.9
    np.testing.assert_allclose(coords[0].reshape(-1, 2).numpy()[ok], uv.reshape(-1, 2)[ok], atol=1e-8)


def _floor_disparity(h, w, fy, cy, height=1.5, pitch=0.0):
    """Inverse depth of a horizontal floor ``height`` below a camera (y down) pitched down by ``pitch`` rad: a
    function of the row alone; rows at or above the horizon see no floor (0)."""
    v = torch.arange(h, dtype=torch.float64)[:, None].expand(h, w)
    ray_y = (v - cy) / fy  # normalised ray (x, ray_y, 1); in a level frame its downward part:
    down = ray_y * torch.cos(torch.tensor(pitch)) + torch.sin(torch.tensor(pitch))
    return (down / height).clamp(min=0)


def test_fill_holes_by_row_recovers_a_floor_the_image_median_does_not():
    from pvslam_core.geometry.projective import fill_holes

    h, w = 12, 16
    disp = _floor_disparity(h, w, fy=14.0, cy=2.5, pitch=0.25)  # the floor fills the view
    assert float(disp.min()) > 0
    hole = torch.zeros(h, w, dtype=torch.bool)
    hole[:, 11:] = True  # a turn brought 5 new columns in
    by_row = fill_holes(disp, hole, row_min_frac=0.25)
    assert torch.allclose(by_row, disp)  # each row's known part is the row's depth
    whole = fill_holes(disp, hole, row_min_frac=0.0)
    assert torch.equal(whole[~hole], disp[~hole])
    assert torch.equal(whole[hole], disp[~hole].median().expand(int(hole.sum())))  # the old rule
    assert float((whole - disp).abs().max()) > 0.1 * float(disp.max())


def test_fill_holes_falls_back_to_the_image_median_on_rows_with_too_few_known_pixels():
    from pvslam_core.geometry.projective import fill_holes

    g = torch.Generator().manual_seed(3)
    disp = 0.2 + torch.rand(6, 10, generator=g, dtype=torch.float64)
    hole = torch.zeros(6, 10, dtype=torch.bool)
    hole[0, :8] = True  # row 0: 2 of 10 known (< 0.25)
    hole[1, :7] = True  # row 1: 3 of 10 known (>= 0.25)
    hole[2:, 9] = True
    out = fill_holes(disp, hole, row_min_frac=0.25)
    whole = disp[~hole].median()
    assert torch.equal(out[0, :8], whole.expand(8))
    assert torch.equal(out[1, :7], disp[1, 7:].median().expand(7))
    for r in range(2, 6):
        assert out[r, 9] == disp[r, :9].median()
    assert torch.equal(out[~hole], disp[~hole])
    assert not torch.isnan(out).any()
    assert torch.equal(fill_holes(disp, torch.zeros_like(hole)), disp)  # nothing to fill
