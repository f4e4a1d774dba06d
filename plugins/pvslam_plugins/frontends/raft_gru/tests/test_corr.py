"""Correlation pyramid / lookup against independent references: a brute-force loop, RAFT's grid_sample lookup."""
from __future__ import annotations

import itertools
import math

import pytest
import torch
import torch.nn.functional as F

from pvslam_plugins.frontends.raft_gru.corr import CorrVolume, OnTheFlyCorr, coords_grid, make_corr

from _raft_gru_testing import assert_close


def _random_case(b=2, n=3, c=16, h=16, w=18, e=4, seed=0, spread=3.0):
    g = torch.Generator().manual_seed(seed)
    fmaps = torch.randn(b, n, c, h, w, generator=g)
    ii = torch.tensor([0, 1, 2, 1][:e])
    jj = torch.tensor([1, 0, 1, 1][:e])  # includes a self-edge (1 -> 1)
    coords = coords_grid(h, w) + spread * torch.randn(b, e, h, w, 2, generator=g)
    coords[0, 0, 0, 0] = torch.tensor([3.0, 5.0])  # an integer point
    coords[0, 0, 0, 1] = torch.tensor([-0.25, -0.75])  # negative fractions
    coords[-1, min(1, e - 1), 2, 2] = torch.tensor([1e3, -1e3])  # far outside
    coords[-1, min(2, e - 1), 3, 3] = torch.tensor([w - 1 + 0.5, h - 1 + 0.5])  # straddling the last row/column
    return fmaps, ii, jj, coords


def _brute_force(fmaps, ii, jj, coords, levels, radius):
    """Float64 scalar loops straight from the definition (module doc of corr.py)."""
    b, n, c, h, w = fmaps.shape
    f = fmaps.double()
    pyr = [f]
    for _ in range(levels - 1):  # pool the features 2x2 (floor): equal to pooling the volume
        p = pyr[-1]
        hh, ww = p.shape[-2] // 2, p.shape[-1] // 2
        pyr.append(p[..., : 2 * hh, : 2 * ww].reshape(b, n, c, hh, 2, ww, 2).mean((4, 6)))
    k = 2 * radius + 1
    out = torch.zeros(b, len(ii), levels * k * k, h, w, dtype=torch.float64)
    for bi, e, y, x in itertools.product(range(b), range(len(ii)), range(h), range(w)):
        src = f[bi, ii[e], :, y, x] / 4
        for lvl in range(levels):
            tgt = pyr[lvl][bi, jj[e]] / 4
            hl, wl = tgt.shape[-2:]
            cx, cy = coords[bi, e, y, x].double().tolist()
            for a, bb in itertools.product(range(k), range(k)):
                px, py = cx / 2**lvl - radius + a, cy / 2**lvl - radius + bb
                x0, y0 = math.floor(px), math.floor(py)
                val = 0.0
                for xx, yy in itertools.product((x0, x0 + 1), (y0, y0 + 1)):
                    if 0 <= xx < wl and 0 <= yy < hl:
                        wgt = (1 - abs(px - xx)) * (1 - abs(py - yy))
                        val += wgt * float(src @ tgt[:, yy, xx])
                out[bi, e, lvl * k * k + a * k + bb, y, x] = val
    return out


def _grid_sample_reference(vol_pyramid, coords, radius):
    """RAFT's CorrBlock lookup (grid_sample, align_corners=True), with DROID's x-major window."""
    b, e, h, w = vol_pyramid[0].shape[:4]
    d = torch.arange(-radius, radius + 1, dtype=torch.float64)
    off = torch.stack(torch.meshgrid(d, d, indexing="ij"), -1)  # [a, b] = (dx=a-r, dy=b-r)
    outs = []
    for lvl, vol in enumerate(vol_pyramid):
        hl, wl = vol.shape[-2:]
        xy = coords.double().reshape(-1, 1, 1, 2) / 2**lvl + off
        grid = torch.stack([2 * xy[..., 0] / (wl - 1) - 1, 2 * xy[..., 1] / (hl - 1) - 1], -1)
        s = F.grid_sample(vol.double().reshape(-1, 1, hl, wl), grid, align_corners=True, padding_mode="zeros")
        outs.append(s.view(b, e, h, w, -1))
    return torch.cat(outs, -1).permute(0, 1, 4, 2, 3)


def test_lookup_matches_brute_force_loops():
    fmaps, ii, jj, coords = _random_case(b=1, n=2, c=8, h=4, w=5, e=2, seed=1, spread=2.0)
    ii, jj = torch.tensor([0, 1]), torch.tensor([1, 1])
    want = _brute_force(fmaps, ii, jj, coords, levels=2, radius=1)
    for impl, kw in (("volume", {}), ("onthefly", {"dense_max_pixels": 0}), ("onthefly", {})):
        got = make_corr(fmaps, ii, jj, impl, num_levels=2, radius=1, **kw)(coords)
        assert_close(f"{impl} {kw} vs brute force", got, want.float(), atol=2e-6)


def test_lookup_matches_grid_sample_reference():
    fmaps, ii, jj, coords = _random_case()
    vol = CorrVolume.from_edges(fmaps, ii, jj)
    want = _grid_sample_reference(vol.pyramid, coords, 3)
    assert_close("volume vs grid_sample", vol(coords), want.float(), atol=1e-5)
    # odd sizes pool with floor: 18 -> 9 -> 4 -> 2 and 16 -> 8 -> 4 -> 2
    assert [tuple(v.shape[-2:]) for v in vol.pyramid] == [(16, 18), (8, 9), (4, 4), (2, 2)]


@pytest.mark.parametrize("kwargs", [{}, {"dense_max_pixels": 0}, {"dense_max_pixels": 0, "chunk_mb": 2.0},
                                    {"chunk_mb": 0.05}])
def test_onthefly_equals_volume(kwargs):
    fmaps, ii, jj, coords = _random_case()
    want = CorrVolume.from_edges(fmaps, ii, jj)(coords)
    got = OnTheFlyCorr(fmaps, ii, jj, **kwargs)(coords)
    assert_close(f"onthefly {kwargs}", got, want, atol=5e-6)


def test_select_and_cat():
    fmaps, ii, jj, coords = _random_case()
    full_v = CorrVolume.from_edges(fmaps, ii, jj)
    full_o = OnTheFlyCorr(fmaps, ii, jj)
    want = full_v(coords)
    idx = torch.tensor([3, 0])
    for corr in (full_v, full_o):
        part = corr.select(idx)
        assert part.num_edges == 2
        assert_close("select", part(coords[:, idx]), want[:, idx], atol=5e-6)
        joined = corr.select(torch.tensor([0, 1])).cat(corr.select(torch.tensor([2, 3])))
        assert_close("cat", joined(coords), want, atol=5e-6)


def test_input_checks():
    fmaps, ii, jj, coords = _random_case()
    with pytest.raises(ValueError, match=r"too small for 4 correlation levels.*coarsest level would be 1x1"):
        CorrVolume.from_edges(fmaps[..., :8, :8], ii, jj)
    with pytest.raises(ValueError, match=r"coords1 must be \(B, E, h, w, 2\)"):
        CorrVolume.from_edges(fmaps, ii, jj)(coords[:, :2])
    with pytest.raises(ValueError, match="impl must be"):
        make_corr(fmaps, ii, jj, impl="cuda")


@pytest.mark.parametrize("impl", ["volume", "onthefly"])
def test_gradients_reach_features_not_coords(impl):
    fmaps, ii, jj, coords = _random_case(b=1, c=8)
    ref = fmaps.clone().requires_grad_(True)
    CorrVolume.from_edges(ref, ii, jj)(coords).square().sum().backward()
    f = fmaps.clone().requires_grad_(True)
    xy = coords.clone().requires_grad_(True)
    out = make_corr(f, ii, jj, impl)(xy)
    out.square().sum().backward()
    assert xy.grad is None  # like upstream's CUDA samplers: no gradient to the coordinates
    assert_close(f"{impl} d/dfmaps", f.grad, ref.grad, atol=1e-4 * ref.grad.abs().max().item())
