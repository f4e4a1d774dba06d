"""The frontend's faster formulations of the same network against upstream's own computation: the
golden fixtures and the plain module calls.

* gate contexts (:class:`GateContext`): the constant input blocks of the ConvGRU gates convolved once;
* correlation levels from pooled features (``CorrVolume(pool="features")``);
* the bilinear lookup on 16-bit volumes in fp32 with fp32 coordinates;
* the upsampling mask made from the kept aggregation features only when needed;
* the motion filter's later steps (``track_iters > 1``) from the keyframe's edge context.
"""
from __future__ import annotations

import copy

import pytest
import torch

from pvslam_core.types import Frame, Intrinsics
from pvslam_plugins.frontends.raft_gru.config import RaftGruConfig
from pvslam_plugins.frontends.raft_gru.corr import CorrVolume, coords_grid
from pvslam_plugins.frontends.raft_gru.frontend import RaftGruFrontend
from pvslam_plugins.frontends.raft_gru.net import droid_motion
from pvslam_plugins.frontends.raft_gru.update import GateContext

from _raft_gru_testing import ATOL, assert_close, assert_eta_close


def _edge_inputs(g):
    ii, jj = g["ii"], g["jj"]
    return g["net"][:, ii], g["inp"][:, ii], g["corr_lookup"], g["motion"], ii, jj


@pytest.mark.parametrize("grouped", [False, True])
def test_edge_gate_context_reproduces_the_golden_update(droid_net, droid_golden, grouped):
    """inp's share of the gates precomputed (per edge, or per run of edges sharing a source keyframe): every output
    of the golden DROID update within the fixture tolerance, and equal to the plain call to float rounding."""
    g = droid_golden
    net, inp, corr, motion, ii, jj = _edge_inputs(g)
    upd = droid_net.update
    with torch.no_grad():
        plain = upd(net, inp, corr, motion, ii, jj)
        if grouped:  # edges 0 and 2 share source 1: reorder to runs [1, 1], [0]
            order = torch.tensor([0, 2, 1])
            net, corr, motion, ii, jj = net[:, order], corr[:, order], motion[:, order], ii[order], jj[order]
            per_src = upd.gate_context(g["inp"][0, [1, 0]])
            ctx = GateContext(per_src.zrq, per_src.const, groups=[2, 1])
        else:
            ctx = upd.gate_context(inp[0])
        out = upd(net, None, corr, motion, ii, jj, ctx=ctx)
    back = torch.argsort(torch.tensor([0, 2, 1])) if grouped else torch.arange(3)
    for k in ("net", "delta", "weight"):
        assert_close(k, getattr(out, k)[:, back], g[f"update_{k}"])
        assert_close(f"{k} vs plain", getattr(out, k)[:, back], getattr(plain, k), atol=ATOL)
    assert_eta_close(out.eta, g["update_eta"])
    assert_close("upmask", out.upmask, g["update_upmask"])


def test_motion_filter_gate_context_equals_plain_first_step(droid_net, droid_golden):
    """The motion filter's step (state net0, zero motion) with net0, inp and the zero motion's features folded in:
    only the correlation features are convolved per frame."""
    g = droid_golden
    net, inp, corr, _, _, _ = _edge_inputs(g)
    upd = droid_net.update
    with torch.no_grad():
        plain = upd(net, inp, corr, None)
        ctx = upd.gate_context(inp[0], net=net[0], zero_motion=True)
        assert set(ctx.const) == {"net", "inp", "motion"} and ctx.glo is not None
        out = upd(net, None, corr, None, ctx=ctx)
    for k in ("net", "delta", "weight"):
        assert_close(k, getattr(out, k), getattr(plain, k), atol=ATOL)
    with pytest.raises(ValueError, match="ctx holds 1 edges"):
        upd(net, None, corr, None, ctx=upd.gate_context(inp[0, :1]))


def test_pvo_gate_context_reproduces_the_golden_update(pvo_update, pvo_golden):
    g = pvo_golden
    with torch.no_grad():
        ctx = pvo_update.gate_context(g["inp_in"][0])
        out = pvo_update(g["net_in"], None, g["corr_in"], g["motion_in"], g["ii"], g["jj"], ctx=ctx)
    assert_close("update_net", out.net, g["update_net"])
    assert_close("update_delta", torch.cat([out.delta, out.delta_dy], -1), g["update_delta"])
    assert_close("update_weight", out.weight, g["update_weight"])
    assert_close("update_delta_m", out.delta_m, g["update_delta_m"])
    assert_eta_close(out.eta, g["update_eta"])


def test_upmask_made_later_from_the_aggregation_features(droid_net, droid_golden):
    net, inp, corr, motion, ii, jj = _edge_inputs(droid_golden)
    with torch.no_grad():
        full = droid_net.update(net, inp, corr, motion, ii, jj)
        lazy = droid_net.update(net, inp, corr, motion, ii, jj, upmask=False)
        assert lazy.upmask is None and lazy.agg_features.shape == (1, 2, 128, 16, 17)
        assert torch.equal(lazy.eta, full.eta)
        assert_close("upmask", droid_net.update.agg.upmask_of(lazy.agg_features), droid_golden["update_upmask"])


def test_feature_pooled_pyramid_reproduces_the_golden_volume(droid_golden):
    g = droid_golden
    f, ii, jj = g["fmaps"], g["ii"], g["jj"]
    vol = CorrVolume(f[:, ii], f[:, jj], pool="features")
    assert torch.equal(vol.pyramid[0][0], CorrVolume(f[:, ii], f[:, jj]).pyramid[0][0])  # level 0: same product
    for i in range(4):
        assert_close(f"corr_pyramid_{i}", vol.pyramid[i][0], g[f"corr_pyramid_{i}"])
    assert_close("corr_lookup", vol(g["coords1"]), g["corr_lookup"])
    with pytest.raises(ValueError, match="pool must be"):
        CorrVolume(f[:, ii], f[:, jj], pool="mean")


def test_bf16_volume_lookup_keeps_subpixel_coordinates(droid_golden):
    """A bf16 volume is sampled at fp32 coordinates with fp32 weights: the result is the fp32 lookup of the same
    (bf16-valued) volume rounded once; coordinates are not rounded to bf16 (9.325 would become 9.3125)."""
    g = droid_golden
    f = g["fmaps"][:, [0]].bfloat16()
    vol16 = CorrVolume(f, f, pool="features")
    vol32 = CorrVolume(f, f, pool="features")
    vol32.pyramid = [v.float() for v in vol16.pyramid]
    coords = coords_grid(16, 17).expand(1, 1, 16, 17, 2).clone()
    coords[..., 0] += 0.3  # x in [0.3, 16.3]
    got, want = vol16(coords), vol32(coords)
    assert got.dtype == torch.bfloat16
    assert_close("bf16 lookup", got.float(), want.bfloat16().float(), atol=0.0)  # one rounding of the fp32 result
    assert torch.tensor(9.325).bfloat16().item() == 9.3125
    a = vol16(torch.full((1, 1, 16, 17, 2), 9.325))
    b = vol16(torch.full((1, 1, 16, 17, 2), 9.3125))
    assert not torch.equal(a, b)


def test_motion_filter_with_two_steps_equals_plain_calls(droid_net, droid_golden):
    """``track_iters = 2``: the first step from the keyframe's filter context, the second (moved state, motion input,
    lookup at the new estimate) from its edge context - both equal to the plain upstream-order calls."""
    net = copy.deepcopy(droid_net)
    rgb = [f.contiguous() for f in droid_golden["images_uint8"][0, :, [2, 1, 0]]]
    intr = Intrinsics(110.0, 110.0, 67.5, 63.5, 136, 128)
    fe = RaftGruFrontend(RaftGruConfig(weights="random", track_iters=2, dynamic={"enabled": False}), model=net)
    fe.add_keyframe(0, Frame(index=0, timestamp=0.0, image=rgb[0], intrinsics=intr), None)
    got = fe.track(Frame(index=1, timestamp=0.1, image=rgb[2], intrinsics=intr), None)
    with torch.no_grad():
        f = net.features(torch.stack([rgb[0], rgb[2]])[None], "rgb")
        vol = CorrVolume(f.fmap[:, [0]], f.fmap[:, [1]])
        c0 = coords_grid(16, 17)
        c1 = c0.expand(1, 1, 16, 17, 2)
        o1 = net.update(f.net[:, [0]], f.inp[:, [0]], vol(c1))
        t1 = c1 + o1.delta
        o2 = net.update(o1.net, f.inp[:, [0]], vol(t1), droid_motion(c0, t1, t1))
    assert_close("target", got.target, (t1 + o2.delta)[0, 0].permute(2, 0, 1), atol=2e-5)
    assert_close("weight", got.weight, o2.weight[0, 0].permute(2, 0, 1))
