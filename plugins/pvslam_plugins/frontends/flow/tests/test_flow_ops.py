"""DIS flow -> BA-resolution targets and forward-backward confidence on images with a known warp."""
import numpy as np
import pytest

from pvslam_plugins.frontends.flow import flow_ops as F

import _flow_scenes as S

BA_H, BA_W = S.H // 8, S.W // 8


def _targets(i0, i1, preset, scale, sigma=1.0):
    dis = F.create_dis(preset)
    g0, g1 = F.to_gray(i0, scale), F.to_gray(i1, scale)
    fwd, bwd = F.compute_flow(dis, g0, g1), F.compute_flow(dis, g1, g0)
    conf, fb = F.fb_consistency(fwd, bwd, sigma * scale)
    tgt, w = F.pool_to_ba(fwd, conf, BA_H, BA_W)
    return tgt, w, conf, fb


def _gt_targets(gt_flow):
    tgt, _ = F.pool_to_ba(gt_flow, np.ones(gt_flow.shape[:2], np.float32), BA_H, BA_W, weighted=False)
    return tgt


def test_pool_to_ba_pixel_centres():
    # a constant flow of (s * a, s * b) full-res px moves every BA pixel by exactly (a, b)
    flow = np.zeros((S.H, S.W, 2), np.float32)
    flow[..., 0], flow[..., 1] = 8 * 1.25, 8 * -0.5
    tgt, w = F.pool_to_ba(flow, np.ones((S.H, S.W), np.float32), BA_H, BA_W)
    xs, ys = np.meshgrid(np.arange(BA_W), np.arange(BA_H))
    np.testing.assert_allclose(tgt[0], xs + 1.25, atol=1e-5)
    np.testing.assert_allclose(tgt[1], ys - 0.5, atol=1e-5)
    np.testing.assert_allclose(w, 1.0)
    # an affine flow: the block average equals the flow at the block-centre X = s x + (s - 1) / 2
    X, Y = np.meshgrid(np.arange(S.W, dtype=np.float32), np.arange(S.H, dtype=np.float32))
    flow = np.stack([0.02 * X + 0.01 * Y, -0.03 * X], -1).astype(np.float32)
    tgt, _ = F.pool_to_ba(flow, np.ones((S.H, S.W), np.float32), BA_H, BA_W)
    Xc, Yc = 8 * xs + 3.5, 8 * ys + 3.5
    np.testing.assert_allclose(tgt[0], (Xc + 0.02 * Xc + 0.01 * Yc - 3.5) / 8, atol=1e-4)
    np.testing.assert_allclose(tgt[1], (Yc - 0.03 * Xc - 3.5) / 8, atol=1e-4)


@pytest.mark.parametrize("preset,scale", [("fast", 0.5), ("fast", 1.0), ("medium", 0.5), ("ultrafast", 1.0)])
@pytest.mark.parametrize(
    "A",
    [
        [[1.0, 0.0, 5.3], [0.0, 1.0, -2.7]],  # sub-pixel shift
        [[1.04, 0.01, 3.0], [-0.01, 1.04, 1.0]],  # zoom + small rotation (forward motion)
        [[0.995, 0.05, 12.0], [-0.05, 0.995, -6.0]],  # rotation + larger shift
    ],
)
def test_targets_exact_for_known_warp(preset, scale, A):
    big = S.texture("astronaut")
    i1, gt = S.affine_view(big, np.array(A))
    tgt, w, _, _ = _targets(S.base(big), i1, preset, scale)
    err = np.linalg.norm(tgt - _gt_targets(gt), axis=0)
    inner, w_in = err[2:-2, 2:-2], w[2:-2, 2:-2]
    assert np.median(inner) < 0.1, np.median(inner)
    assert np.average(inner, weights=w_in) < 0.15
    assert w_in.mean() > 0.5


def test_fb_confidence_low_outside_and_occluded():
    big = S.texture("astronaut")
    dx = 24.0
    i0 = S.base(big)
    i1 = S.shifted(big, dx)
    # occluder: a textured patch that appears only in i1 (covers background pixels of i0)
    patch = S.texture("coffee", (60, 60))
    i1 = S.with_patch(i1, patch, 150, 90)
    _, w, conf, fb = _targets(i0, i1, "fast", 1.0)
    # pixels whose shifted position leaves the image (last dx columns) have zero confidence
    assert conf[:, -int(dx) + 1:].max() == 0.0
    assert np.isinf(fb[:, -int(dx) + 1:]).all()
    # pixels of i0 that land under the occluder (x + dx in [150, 210), y in [90, 150)) are inconsistent
    occ = conf[95:145, 130:180]
    free = conf[20:80, 20:200]
    assert occ.mean() < 0.35 * free.mean(), (occ.mean(), free.mean())
    assert free.mean() > 0.7


def test_init_flow_recovers_large_displacement():
    big = S.texture("astronaut")
    i0 = S.base(big)
    # a 70 px jump with zoom and rotation: DIS from zero init fails (OpenCV's calc(I0, I1, flow) uses `flow` as init)
    i1, gt = S.affine_view(big, np.array([[1.1, 0.02, 70.0], [-0.02, 1.1, 25.0]]))
    dis = F.create_dis("fast")
    g0, g1 = F.to_gray(i0), F.to_gray(i1)
    X, Y = np.meshgrid(np.arange(S.W), np.arange(S.H))
    inside = (gt[..., 0] + X >= 0) & (gt[..., 0] + X < S.W) & (gt[..., 1] + Y >= 0) & (gt[..., 1] + Y < S.H)
    zero = F.compute_flow(dis, g0, g1)
    # a rough initialisation (BA-res correspondence field with a 1 BA px bias), upsampled to the flow resolution
    coords = _gt_targets(gt).transpose(1, 2, 0) + 1.0
    init = F.init_flow_from_coords(coords, np.ones((BA_H, BA_W), bool), S.H, S.W)
    with_init = F.compute_flow(dis, g0, g1, init)
    e0 = np.median(np.linalg.norm(zero - gt, axis=-1)[inside])
    e1 = np.median(np.linalg.norm(with_init - gt, axis=-1)[inside])
    assert e0 > 20.0 and e1 < 1.0, (e0, e1)


def test_init_flow_from_coords_fills_invalid_and_rejects():
    xs, ys = np.meshgrid(np.arange(BA_W, dtype=np.float32), np.arange(BA_H, dtype=np.float32))
    coords = np.stack([xs + 2.0, ys - 1.0], -1)
    valid = np.ones((BA_H, BA_W), bool)
    valid[:5] = False
    coords[:5] = np.nan
    f = F.init_flow_from_coords(coords, valid, S.H // 2, S.W // 2)
    assert f.shape == (S.H // 2, S.W // 2, 2)
    np.testing.assert_allclose(f[..., 0], 8.0, atol=1e-4)  # 2 BA px = 8 px at half resolution
    np.testing.assert_allclose(f[..., 1], -4.0, atol=1e-4)
    valid[:] = False
    assert F.init_flow_from_coords(coords, valid, S.H, S.W) is None


def test_downsample_ids_block_centre():
    import torch

    ids = torch.arange(S.H * S.W, dtype=torch.int64).reshape(S.H, S.W)
    d = F.downsample_ids(ids, BA_H, BA_W)
    assert d.shape == (BA_H, BA_W)
    assert int(d[0, 0]) == 4 * S.W + 4 and int(d[1, 2]) == 12 * S.W + 20


def test_create_dis_finest_scale():
    assert F.create_dis("medium", finest_scale=2).getFinestScale() == 2
    assert F.create_dis("medium").getFinestScale() == F.create_dis("medium", finest_scale=None).getFinestScale()
    with pytest.raises(ValueError):
        F.create_dis("slow")


def test_invert_coords_round_trip():
    xs, ys = np.meshgrid(np.arange(BA_W, dtype=np.float32), np.arange(BA_H, dtype=np.float32))
    coords = np.stack([xs + 2.3 + 0.02 * xs, ys - 1.2], -1)
    valid = np.ones((BA_H, BA_W), bool)
    back, vb = F.invert_coords(coords, valid)
    assert vb.mean() > 0.8
    assert not vb[:, :2].any()  # nothing maps there
    # composing: back(coords(x)) ~ x
    fx = back[vb][:, 0] + (2.3 + 0.02 * back[vb][:, 0])
    np.testing.assert_allclose(fx, xs[vb], atol=0.05)
    np.testing.assert_allclose(back[vb][:, 1] - 1.2, ys[vb], atol=1e-5)


def test_photometric_confidence_flags_wrong_flow_and_ignores_brightness_offset():
    big = S.texture("astronaut")
    i1, gt = S.affine_view(big, np.array([[1.0, 0.0, 6.0], [0.0, 1.0, 2.0]]))
    g0, g1 = F.to_gray(S.base(big)), F.to_gray(i1)
    right = F.photometric_confidence(g0, g1, gt, 4.0)
    wrong = F.photometric_confidence(g0, g1, gt * 0.0 + np.float32([1.0, -3.0]), 4.0)
    inner = (slice(10, -10), slice(10, -20))
    assert right[inner].mean() > 0.8 and wrong[inner].mean() < 0.4, (right[inner].mean(), wrong[inner].mean())
    brighter = np.clip(g1.astype(np.int16) + 25, 0, 255).astype(np.uint8)
    assert F.photometric_confidence(g0, brighter, gt, 4.0)[inner].mean() > 0.75
    # an exposure step (gain) is removed as well; a wrong flow under it is still flagged
    for gain in (0.5, 1.5):  # at 1.5 a third of the image saturates: those pixels lost their texture
        scaled = np.clip(g1.astype(np.float32) * gain + 3, 0, 255).astype(np.uint8)
        unsat = (g0.astype(np.float32) * gain + 3 < 250)[inner]
        assert F.photometric_confidence(g0, scaled, gt, 4.0)[inner][unsat].mean() > 0.75, gain
        wrong_g = F.photometric_confidence(g0, scaled, gt * 0.0 + np.float32([1.0, -3.0]), 4.0)
        assert wrong_g[inner].mean() < 0.4, gain


def test_fit_exposure_recovers_gain_and_offset_despite_outliers():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 200, 4000).astype(np.float32)
    y = 0.7 * x + 12 + rng.normal(0, 1.0, x.shape).astype(np.float32)
    y[:800] = rng.uniform(0, 255, 800)  # 20 % wrong matches (occlusions)
    gain, offset = F.fit_exposure(x, y)
    assert abs(gain - 0.7) < 0.02 and abs(offset - 12) < 1.5, (gain, offset)
    assert F.fit_exposure(x, x + 5)[0] == pytest.approx(1.0, abs=1e-3)
    # a wrong flow pairs unrelated pixels: a shrunken gain that would explain them is refused (correlation 0.51)
    loose = (0.4 * x + 60 + rng.normal(0, 40, x.shape)).astype(np.float32)
    assert F.fit_exposure(x, loose)[0] == 1.0 and F.fit_exposure(x, loose, min_corr=0.0)[0] < 0.5
    flat = np.full(100, 80, np.float32)  # no contrast: offset only
    assert F.fit_exposure(flat, flat * 1.5) == (1.0, pytest.approx(40.0))


def test_zero_init_flow_does_not_depend_on_earlier_initialised_calls():
    """OpenCV's DIS reuses the initial flow of an earlier call in later calls without one; the frontend keeps a DIS
    object for initialised calls only, so its zero-init flows are a function of the two images alone."""
    import cv2

    from pvslam_plugins.frontends.flow.frontend import FlowFrontend

    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur((rng.random((120, 160)) * 255).astype(np.uint8), (0, 0), 2.0)
    g0, g1 = base, np.roll(base, 3, axis=1)
    p = FlowFrontend().pairs
    clean = FlowFrontend().pairs.flow("edge", g0, g1)
    init = rng.normal(0, 3, (120, 160, 2)).astype(np.float32)
    p.flows(p.pair_calls(g1, g0, init, init))  # an initialised edge first
    p.flows(p.pair_calls(g1, g0, init, init, kind="track"))
    np.testing.assert_array_equal(p.flow("edge", g0, g1), clean)
    np.testing.assert_array_equal(p.flow("track", g0, g1), clean)


def _half_textured():
    """120 x 160 gray: fine random texture on the left half, flat on the right."""
    import cv2

    rng = np.random.default_rng(0)
    img = np.full((120, 160), 128, np.uint8)
    img[:, :80] = cv2.GaussianBlur((rng.random((120, 80)) * 255).astype(np.uint8), (0, 0), 1.0)
    return img


def test_texture_confidence_weights_texture_and_adapts_to_a_bare_image():
    img = _half_textured()
    tex, flat = (slice(10, -10), slice(10, 70)), (slice(10, -10), slice(90, -10))
    c = F.texture_confidence(img, 3e-4)
    assert c[tex].mean() > 0.8 and c[flat].max() < 0.05
    # the same pattern at 1/20 of the contrast (a bare room): a fixed tau scales every weight towards zero, the
    # image's own quantile keeps its better-textured pixels useful and the flat ones still at zero
    faint = (128 + (img.astype(np.float32) - 128) * 0.05).round().astype(np.uint8)
    fixed, rel = F.texture_confidence(faint, 3e-4), F.texture_confidence(faint, 3e-4, quantile=0.75)
    assert fixed[tex].mean() < 0.05 and rel[tex].mean() > 0.4 and rel[flat].max() < 0.05
    # where the image's texture is strong the quantile does not bind: the same weights as the fixed tau
    np.testing.assert_array_equal(F.texture_confidence(img, 3e-4, quantile=0.9), c)
