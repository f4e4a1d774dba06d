"""Every tensor of ``droid_net_golden.pt`` (upstream DROID-SLAM ``DroidNet`` on seeded weights) reproduced."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.frontends.raft_gru import CorrVolume, OnTheFlyCorr, coords_grid, cvx_upsample, upsample_disp
from pvslam_plugins.frontends.raft_gru.encoders import frames_to_images
from pvslam_plugins.frontends.raft_gru.net import droid_motion

from _raft_gru_testing import CHAIN_ATOL, assert_close, assert_eta_close

UPDATE_KEYS = ("net", "delta", "weight", "eta", "upmask")


def test_state_dict_layout_equals_upstream(droid_golden, droid_net):
    want = droid_golden["state_dict"]
    got = droid_net.state_dict()
    assert list(got) == list(want)  # same names, same order
    assert all(got[k].shape == want[k].shape for k in want)
    assert len(got) == droid_golden["meta"]["num_tensors"] == 102
    assert sum(p.numel() for p in droid_net.parameters()) == droid_golden["meta"]["num_params"] == 4_002_565


def test_features(droid_golden, droid_features):
    assert_close("fmaps", droid_features.fmap, droid_golden["fmaps"], atol=CHAIN_ATOL)
    assert_close("net", droid_features.net, droid_golden["net"], atol=CHAIN_ATOL)
    assert_close("inp", droid_features.inp, droid_golden["inp"], atol=CHAIN_ATOL)


def test_float_input_fmap_only_and_context_only(droid_golden, droid_net):
    with torch.no_grad():
        f = droid_net.features(droid_golden["images_uint8"].float(), context=False)  # upstream was fed .float()
        net, inp = droid_net.context(droid_golden["images_uint8"])
    assert f.net is None and f.inp is None
    assert_close("fmaps (float input)", f.fmap, droid_golden["fmaps"], atol=CHAIN_ATOL)
    assert_close("net (context only)", net, droid_golden["net"], atol=CHAIN_ATOL)
    assert_close("inp (context only)", inp, droid_golden["inp"], atol=CHAIN_ATOL)


def test_rgb_frames_equal_bgr_images(droid_golden, droid_net, droid_features):
    """pvslam frames are RGB: the same picture given as RGB frames gives the same features."""
    frames = [f for f in droid_golden["images_uint8"][0, :, [2, 1, 0]]]  # three uint8 [3, H, W] RGB frames
    with torch.no_grad():
        b = droid_net.features(frames_to_images(frames), channel_order="rgb")
        wrong = droid_net.features(frames_to_images(frames), channel_order="bgr", context=False)
    a = droid_features
    assert torch.equal(a.fmap, b.fmap) and torch.equal(a.net, b.net) and torch.equal(a.inp, b.inp)
    assert (wrong.fmap - a.fmap).abs().max() > 0.1  # the order matters, so the test can fail


def test_coords_grid_and_motion(droid_golden):
    coords0 = coords_grid(16, 17)
    assert torch.equal(coords0, droid_golden["coords0"])
    motion = droid_motion(coords0, droid_golden["coords1"], droid_golden["target"])
    assert_close("motion", motion, droid_golden["motion"], atol=0.0)


def test_corr_pyramid(droid_golden):
    ii, jj = droid_golden["ii"], droid_golden["jj"]
    vol = CorrVolume.from_edges(droid_golden["fmaps"], ii, jj)
    for i in range(4):
        assert_close(f"corr_pyramid_{i}", vol.pyramid[i][0], droid_golden[f"corr_pyramid_{i}"])


@pytest.mark.parametrize(
    "impl, kwargs",
    [
        ("volume", {}),
        ("onthefly", {}),  # all 4 levels dense per chunk at this size
        ("onthefly", {"dense_max_pixels": 0}),  # all levels by the (2r+2)^2 window gather
        ("onthefly", {"dense_max_pixels": 0, "chunk_mb": 1.0}),  # window gather in 26 chunks per level
        ("onthefly", {"chunk_mb": 0.05}),  # dense, chunked inside one edge
    ],
)
def test_corr_lookup(droid_golden, impl, kwargs):
    ii, jj = droid_golden["ii"], droid_golden["jj"]
    fmaps = droid_golden["fmaps"]
    corr = CorrVolume.from_edges(fmaps, ii, jj) if impl == "volume" else OnTheFlyCorr(fmaps, ii, jj, **kwargs)
    assert_close(f"corr_lookup[{impl}, {kwargs}]", corr(droid_golden["coords1"]), droid_golden["corr_lookup"])


@pytest.mark.parametrize("strided", [False, True])
def test_update(droid_golden, droid_net, strided):
    g = droid_golden
    ii, jj = g["ii"], g["jj"]
    # strided: upstream's motion tensor strides (permute then clamp), which makes CPU conv bitwise equal.
    motion = droid_motion(coords_grid(16, 17), g["coords1"], g["target"]) if strided else g["motion"]
    with torch.no_grad():
        out = droid_net.update(g["net"][:, ii], g["inp"][:, ii], g["corr_lookup"], motion, ii, jj)
    for k in ("net", "delta", "weight", "upmask"):
        assert_close(f"update_{k}", getattr(out, k), g[f"update_{k}"])
    assert_eta_close(out.eta, g["update_eta"])
    assert out.frames.tolist() == [0, 1]  # maps per unique ii, ascending
    assert out.weight_is_logit is False and out.delta_dy is None and out.delta_m is None
    got = out.as_upstream()
    assert len(got) == 5 and got[1] is out.delta


def test_update_without_ii_equals_with_ii(droid_golden, droid_net):
    g = droid_golden
    ii = g["ii"]
    args = (g["net"][:, ii], g["inp"][:, ii], g["corr_lookup"], g["motion"])
    with torch.no_grad():
        a = droid_net.update(*args, ii, g["jj"])
        b = droid_net.update(*args)
    assert b.eta is None and b.upmask is None and len(b.as_upstream()) == 3
    assert torch.equal(a.net, b.net) and torch.equal(a.delta, b.delta) and torch.equal(a.weight, b.weight)


def test_whole_chain_from_images(droid_golden, droid_net, droid_features):
    """Our features -> our correlation (both paths) -> our update, against upstream's stored update."""
    g, f = droid_golden, droid_features
    ii, jj = g["ii"], g["jj"]
    with torch.no_grad():
        motion = droid_motion(coords_grid(16, 17), g["coords1"], g["target"])
        for impl in ("volume", "onthefly"):
            corr = droid_net.correlation(f.fmap, ii, jj, impl=impl)(g["coords1"])
            out = droid_net(f.net[:, ii], f.inp[:, ii], corr, motion, ii, jj)
            for k in ("net", "delta", "weight", "upmask"):
                assert_close(f"chain[{impl}] {k}", getattr(out, k), g[f"update_{k}"])
            assert_eta_close(out.eta, g["update_eta"])


def test_upsampling(droid_golden):
    g = droid_golden
    assert_close("disps_up", upsample_disp(g["disps"], g["update_upmask"]), g["disps_up"])
    mask = g["update_upmask"][0, :1, :, :6, :7].contiguous()
    assert_close("cvx_up", cvx_upsample(g["cvx_data_in"], mask), g["cvx_up"])
