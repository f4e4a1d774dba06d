"""Every tensor of ``pvo_update_golden.pt`` (upstream PVO ``DynamicUpdateModule``) reproduced, and PVO key layouts."""
from __future__ import annotations

import torch

from pvslam_plugins.frontends.raft_gru import RaftGruNet, upsample_disp, upsample_inter
from pvslam_plugins.frontends.raft_gru.net import pvo_motion
from pvslam_plugins.frontends.raft_gru.update import UpdateModule

from _raft_gru_testing import assert_close, assert_eta_close


def _call(pvo_update, g, with_ii=True):
    args = (g["net_in"], g["inp_in"], g["corr_in"], g["motion_in"])
    with torch.no_grad():
        return pvo_update(*args, g["ii"], g["jj"]) if with_ii else pvo_update(*args)


def test_update_outputs(pvo_update, pvo_golden):
    g = pvo_golden
    out = _call(pvo_update, g)
    assert out.weight_is_logit
    net, delta4, weight, eta, upmask, delta_m = out.as_upstream()
    assert_close("update_net", net, g["update_net"])
    assert_close("update_delta (4 ch)", delta4, g["update_delta"])
    assert_close("delta = channels 0-1", out.delta, g["update_delta"][..., :2])
    assert_close("delta_dy = channels 2-3", out.delta_dy, g["update_delta"][..., 2:])
    assert_close("update_weight (raw logits)", weight, g["update_weight"])
    assert_eta_close(eta, g["update_eta"])
    assert set(upmask) == {"disp", "flow", "dy_mask"} and upmask["flow"] is None and upmask["dy_mask"] is None
    assert_close("update_upmask_disp", upmask["disp"], g["update_upmask_disp"])
    assert_close("update_delta_m", delta_m, g["update_delta_m"])
    assert out.frames.tolist() == [0, 1]


def test_mask_and_bilinear_upsampling(pvo_update, pvo_golden):
    g = pvo_golden
    out = _call(pvo_update, g)
    mask = torch.sigmoid(g["raw_mask_in"] + out.delta_m)
    assert_close("mask_lowres", mask, g["mask_lowres"])
    assert_close("mask_up", upsample_inter(g["mask_lowres"]), g["mask_up"])


def test_without_ii_equals_with_ii(pvo_update, pvo_golden):
    a = _call(pvo_update, pvo_golden)
    b = _call(pvo_update, pvo_golden, with_ii=False)
    net, delta4, weight, delta_m = b.as_upstream()
    assert torch.equal(net, a.net) and torch.equal(weight, a.weight) and torch.equal(delta_m, a.delta_m)
    assert torch.equal(delta4, torch.cat([a.delta, a.delta_dy], -1))


def test_motion_channel_layout(pvo_golden):
    """motion_in = [cam_flow, cam_flow + delta_dy, resd, raw_mask]; channels 6-7 are raw_mask_in."""
    m = pvo_golden["motion_in"].permute(0, 1, 3, 4, 2)  # (B, E, h, w, 8)
    rebuilt = pvo_motion(m[..., 0:2], m[..., 2:4] - m[..., 0:2], m[..., 4:6], pvo_golden["raw_mask_in"])
    assert_close("motion_in", rebuilt, pvo_golden["motion_in"], atol=1e-5)
    assert torch.equal(m[..., 6:8], pvo_golden["raw_mask_in"])


def test_key_inventories(pvo_golden):
    meta = pvo_golden["meta"]
    upd = UpdateModule("pvo").state_dict()
    assert [(k, list(v.shape)) for k, v in upd.items()] == [(k, list(s)) for k, s in meta["update_keys"]]
    aff = UpdateModule("pvo", use_aff_bri=True).state_dict()
    assert [(k, list(v.shape)) for k, v in aff.items()] == [(k, list(s)) for k, s in meta["update_keys_use_aff_bri"]]
    full = RaftGruNet("pvo").state_dict()
    assert [(k, list(v.shape)) for k, v in full.items()] == [(k, list(s)) for k, s in meta["droidnet_keys"]]
    droid = RaftGruNet("droid").state_dict()
    diff = meta["key_diff_vs_droid_droidnet"]
    assert sorted(set(droid) - set(full)) == sorted(diff["only_in_droid"])
    assert sorted(set(full) - set(droid)) == sorted(diff["only_in_pvo"])


def test_full_pvo_net_and_aff_bri_head(pvo_full_state_dict, pvo_golden):
    model = RaftGruNet("pvo")
    model.load_state_dict(pvo_full_state_dict, strict=True)
    g = pvo_golden
    with torch.no_grad():
        out = model(g["net_in"], g["inp_in"], g["corr_in"], g["motion_in"], g["ii"], g["jj"])
    assert_close("update_net via RaftGruNet", out.net, g["update_net"])
    assert model.motion_dim == 8
    # use_aff_bri (no golden numbers stored): shape and range of the affine parameters, other outputs unchanged.
    aff = UpdateModule("pvo", use_aff_bri=True)
    missing, unexpected = aff.load_state_dict(model.update.state_dict(), strict=False)
    assert unexpected == [] and all(k.startswith(("global_avg_pool.", "param_linear.")) for k in missing)
    with torch.no_grad():
        o = aff(g["net_in"], g["inp_in"], g["corr_in"], g["motion_in"], g["ii"], g["jj"])
    assert o.aff_params.shape == (1, 3, 2) and bool(((o.aff_params > 0) & (o.aff_params < 1)).all())
    assert torch.equal(o.net, out.net) and len(o.as_upstream()) == 7


def test_disp_upsampling_is_droids(pvo_golden):
    """PVO's upsample_dim_1 equals DROID's upsample_disp: a constant disparity stays constant (convex weights)."""
    mask = pvo_golden["update_upmask_disp"]
    disp = torch.full(mask.shape[:2] + mask.shape[-2:], 0.7)
    up = upsample_disp(disp, mask)
    # interior only: the 3x3 unfold zero-pads at the border
    assert_close("constant disp", up[..., 8:-8, 8:-8], torch.full_like(up[..., 8:-8, 8:-8], 0.7), atol=1e-6)
