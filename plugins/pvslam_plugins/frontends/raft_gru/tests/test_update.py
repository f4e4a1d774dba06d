"""Update-operator pieces against brute-force references: graph aggregation, gradient clipping, upsampling."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from pvslam_plugins.frontends.raft_gru import cvx_upsample, upsample_flow, upsample_inter
from pvslam_plugins.frontends.raft_gru.encoders import check_image_size, frames_to_images
from pvslam_plugins.frontends.raft_gru.net import RaftGruNet
from pvslam_plugins.frontends.raft_gru.update import GradientClip, GraphAgg, UpdateModule

from _raft_gru_testing import assert_close


def test_gradient_clip_identity_forward_clipped_backward():
    x = torch.tensor([1.0, 2.0, 3.0, 4.0], requires_grad=True)
    y = GradientClip()(x)
    assert torch.equal(y, x)
    g = torch.tensor([0.005, -0.02, float("nan"), -0.01])
    y.backward(g)
    assert torch.equal(x.grad, torch.tensor([g[0].item(), 0.0, 0.0, g[3].item()]))  # |g| > 0.01, NaN -> 0


def test_graph_agg_matches_per_frame_loop():
    torch.manual_seed(0)
    agg = GraphAgg().eval()
    net = torch.randn(2, 5, 128, 3, 4)
    ii = torch.tensor([4, 0, 4, 2, 4])  # unsorted, repeated
    with torch.no_grad():
        eta, upmask, frames = agg(net, ii)
        assert frames.tolist() == [0, 2, 4]
        for u, fr in enumerate(frames.tolist()):
            edges = (ii == fr).nonzero().flatten()
            mean = torch.stack([F.relu(agg.conv1(net[:, e])) for e in edges]).mean(0)
            x = F.relu(agg.conv2(mean))
            assert_close(f"eta frame {fr}", eta[:, u], 0.01 * F.softplus(agg.eta[0](x))[:, 0], atol=1e-7)
            assert_close(f"upmask frame {fr}", upmask[:, u], agg.upmask[0](x), atol=1e-5)


def test_update_shape_checks_and_defaults():
    torch.manual_seed(0)
    mod = UpdateModule("droid").eval()
    net, inp = torch.randn(1, 2, 128, 4, 5), torch.randn(1, 2, 128, 4, 5)
    corr = torch.randn(1, 2, 196, 4, 5)
    with torch.no_grad():
        a = mod(net, inp, corr)  # motion None = zeros, as upstream
        b = mod(net, inp, corr, torch.zeros(1, 2, 4, 4, 5))
    assert torch.equal(a.delta, b.delta) and a.delta.shape == (1, 2, 4, 5, 2)
    assert bool(((a.weight > 0) & (a.weight < 1)).all())
    with pytest.raises(ValueError, match=r"motion must be \(1, 2, 4, 4, 5\) for variant 'droid'"):
        mod(net, inp, corr, torch.zeros(1, 2, 8, 4, 5))
    with pytest.raises(ValueError, match="corr must be"):
        mod(net, inp, corr[:, :, :100])
    with pytest.raises(ValueError, match="ii has 3 entries for 2 edges"):
        mod(net, inp, corr, None, torch.tensor([0, 1, 2]))
    with pytest.raises(ValueError, match="use_aff_bri exists only"):
        UpdateModule("droid", use_aff_bri=True)


def test_update_is_trainable():
    torch.manual_seed(0)
    model = RaftGruNet("pvo")
    net, inp = torch.randn(1, 2, 128, 4, 5), torch.randn(1, 2, 128, 4, 5)
    out = model(net, inp, torch.randn(1, 2, 196, 4, 5), torch.randn(1, 2, 8, 4, 5), torch.tensor([0, 1]))
    loss = out.delta.square().mean() + out.weight.mean() + out.delta_m.mean() + out.eta.mean() + out.upmask.mean()
    (0.01 * loss).backward()  # small enough that GradientClip (|g| > 0.01 -> 0) keeps the head gradients
    for name in ("update.delta.2.weight", "update.gru.convz.weight", "update.agg.eta.0.weight",
                 "update.flow_encoder.0.weight", "update.delta_mask.0.weight"):
        grad = dict(model.named_parameters())[name].grad
        assert grad is not None and bool(torch.isfinite(grad).all()) and grad.abs().sum() > 0, name


def test_cvx_upsample_matches_definition():
    torch.manual_seed(0)
    b, h, w, d = 1, 2, 3, 2
    data, mask = torch.randn(b, h, w, d), torch.randn(b, 576, h, w)
    up = cvx_upsample(data, mask)
    padded = F.pad(data.permute(0, 3, 1, 2), (1, 1, 1, 1))  # zero padding, (B, D, h+2, w+2)
    for y, x, a, bb in [(0, 0, 0, 0), (1, 2, 7, 3), (0, 1, 5, 6), (1, 0, 2, 7)]:
        logits = torch.stack([mask[0, k * 64 + a * 8 + bb, y, x] for k in range(9)])
        wk = torch.softmax(logits, 0)
        val = sum(wk[3 * ky + kx] * padded[0, :, y + ky, x + kx] for ky in range(3) for kx in range(3))
        assert_close(f"pixel ({8 * y + a}, {8 * x + bb})", up[0, 8 * y + a, 8 * x + bb], val, atol=1e-6)
    flow = data[:, None].expand(1, 3, h, w, d).contiguous()
    up_n = upsample_flow(flow, mask[:, None].expand(1, 3, 576, h, w))
    assert up_n.shape == (1, 3, 16, 24, 2) and torch.equal(up_n[:, 1], up)


def test_upsample_inter_equals_scale_factor_form():
    x = torch.randn(1, 2, 5, 7, 3)
    want = F.interpolate(x.permute(0, 1, 4, 2, 3).reshape(2, 3, 5, 7), scale_factor=8, mode="bilinear",
                         align_corners=True, recompute_scale_factor=True).permute(0, 2, 3, 1).reshape(1, 2, 40, 56, 3)
    assert torch.equal(upsample_inter(x), want)


def test_image_checks():
    with pytest.raises(ValueError, match="not a multiple of 8"):
        check_image_size(130, 136)
    assert frames_to_images([torch.zeros(3, 8, 8, dtype=torch.uint8)] * 2).shape == (1, 2, 3, 8, 8)
    model = RaftGruNet()
    with pytest.raises(ValueError, match="too small for 4 correlation levels"):
        model.features(torch.zeros(1, 1, 3, 64, 136, dtype=torch.uint8))
    with pytest.raises(ValueError, match="channel_order"):
        model.features(torch.zeros(1, 1, 3, 128, 128, dtype=torch.uint8), channel_order="yuv")
