"""The golden chain on every available device (CUDA where present: issue target "the same fixtures pass on CUDA"),
and autocast plumbing."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.frontends.raft_gru import RaftGruNet, coords_grid, cvx_upsample, upsample_disp, upsample_inter
from pvslam_plugins.frontends.raft_gru.net import droid_motion
from pvslam_plugins.frontends.raft_gru.update import UpdateModule

from _raft_gru_testing import CHAIN_ATOL, assert_close, assert_eta_close

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")),
]


@pytest.fixture
def exact_fp32():
    """TF32 off for the comparison (Ampere+ GPUs use it for fp32 convs/matmuls by default: ~1e-3 errors)."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@pytest.mark.parametrize("device", DEVICES)
def test_golden_chain_on_device(device, exact_fp32, droid_golden, pvo_golden, pvo_update_state_dict):
    g = {k: v.to(device) if torch.is_tensor(v) else v for k, v in droid_golden.items()}
    model = RaftGruNet("droid")
    model.load_state_dict(droid_golden["state_dict"])
    model.to(device).eval()
    ii, jj = g["ii"], g["jj"]
    with torch.no_grad():
        f = model.features(g["images_uint8"])
        for name, got in (("fmaps", f.fmap), ("net", f.net), ("inp", f.inp)):
            assert got.device.type == device
            assert_close(f"{device} {name}", got, g[name], atol=CHAIN_ATOL)
        for impl in ("volume", "onthefly"):
            corr = model.correlation(g["fmaps"], ii, jj, impl=impl)
            assert_close(f"{device} corr_lookup[{impl}]", corr(g["coords1"]), g["corr_lookup"])
        motion = droid_motion(coords_grid(16, 17, device=device), g["coords1"], g["target"])
        out = model(g["net"][:, ii], g["inp"][:, ii], g["corr_lookup"], motion, ii, jj)
        for k in ("net", "delta", "weight", "upmask"):
            assert_close(f"{device} update_{k}", getattr(out, k), g[f"update_{k}"])
        assert_eta_close(out.eta, g["update_eta"])
        assert_close(f"{device} disps_up", upsample_disp(g["disps"], g["update_upmask"]), g["disps_up"])
        mask = g["update_upmask"][0, :1, :, :6, :7].contiguous()
        assert_close(f"{device} cvx_up", cvx_upsample(g["cvx_data_in"], mask), g["cvx_up"])

        p = {k: v.to(device) if torch.is_tensor(v) else v for k, v in pvo_golden.items()}
        pvo = UpdateModule("pvo")
        pvo.load_state_dict(pvo_update_state_dict)
        pvo.to(device).eval()
        o = pvo(p["net_in"], p["inp_in"], p["corr_in"], p["motion_in"], p["ii"], p["jj"])
        assert_close(f"{device} pvo net", o.net, p["update_net"])
        assert_close(f"{device} pvo delta", torch.cat([o.delta, o.delta_dy], -1), p["update_delta"])
        assert_close(f"{device} pvo weight", o.weight, p["update_weight"])
        assert_close(f"{device} pvo upmask_disp", o.upmask, p["update_upmask_disp"])
        assert_close(f"{device} pvo delta_m", o.delta_m, p["update_delta_m"])
        assert_eta_close(o.eta, p["update_eta"], "pvo eta")
        assert_close(f"{device} mask_up", upsample_inter(p["mask_lowres"]), p["mask_up"])


def test_runs_under_autocast(droid_golden, droid_net):
    """bf16 autocast on the CPU (fp16 on CUDA works the same way): no dtype clashes, results near fp32."""
    g = droid_golden
    ii, jj = g["ii"], g["jj"]
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        f = droid_net.features(g["images_uint8"])
        motion = droid_motion(coords_grid(16, 17), g["coords1"], g["target"])
        for impl in ("volume", "onthefly"):
            corr = droid_net.correlation(f.fmap, ii, jj, impl=impl)(g["coords1"])
            out = droid_net(f.net[:, ii], f.inp[:, ii], corr, motion, ii, jj)
            assert out.delta.dtype == torch.bfloat16
            assert (out.delta.float() - g["update_delta"]).abs().max() < 0.2  # delta spans [-2.9, 1.6]
            assert (out.weight.float() - g["update_weight"]).abs().max() < 0.05
            assert_close("eta (bf16)", out.eta.float(), g["update_eta"], atol=1e-3)
