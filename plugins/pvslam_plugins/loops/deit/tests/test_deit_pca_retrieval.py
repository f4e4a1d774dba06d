"""PCA / whitening (fixed and online) and the id-keyed retrieval: threshold, temporal exclusion, removal."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.loops.deit.config import RetrievalConfig
from pvslam_plugins.loops.deit.pca import OnlinePCA, PCAWhitening
from pvslam_plugins.loops.deit.retrieval import KeyframeIndex, LoopRetrieval


def _data(n: int = 200, d: int = 12, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    mix = torch.randn(d, d, generator=g) * torch.logspace(0, -2, d)[None]  # anisotropic, correlated
    return (torch.randn(n, d, generator=g) @ mix.T + 3.0).double()


def test_whitening_gives_identity_covariance_on_the_fit_set():
    x = _data()
    pca = PCAWhitening.fit(x, whiten=True, shrinkage=0.0)
    y = pca.transform(x).double()
    assert y.shape == (200, 12)
    cov = (y - y.mean(0)).T @ (y - y.mean(0)) / len(y)  # population covariance, as documented
    assert torch.allclose(cov, torch.eye(12, dtype=torch.float64), atol=1e-3)
    assert y.mean(0).abs().max() < 1e-4


def test_pca_matches_an_svd_reference_and_keeps_variances():
    x = _data()
    pca = PCAWhitening.fit(x, dim=5, whiten=False)
    xc = x - x.mean(0)
    _, s, vt = torch.linalg.svd(xc, full_matrices=False)
    ref_var = s[:5] ** 2 / len(x)
    assert torch.allclose(pca.eigenvalues.double(), ref_var, rtol=1e-4)
    # same subspace and, up to the sign convention, the same axes
    dots = (pca.components.double() * vt[:5]).sum(1).abs()
    assert torch.allclose(dots, torch.ones(5, dtype=torch.float64), atol=1e-4)
    y = pca.transform(x).double()
    assert torch.allclose(y.var(0, unbiased=False), ref_var, rtol=1e-4)  # no whitening: variances kept
    # shrinkage only damps the weak directions: the top one is barely touched, the weakest much more
    shr = PCAWhitening.fit(x, dim=5, whiten=True, shrinkage=0.5).transform(x).double().var(0, unbiased=False)
    assert 0.75 < shr[0] <= 1.0 and shr[-1] < 0.5


def test_rank_deficient_fit_is_capped_and_save_load(tmp_path):
    x = _data(n=6, d=12)
    pca = PCAWhitening.fit(x, dim=10)
    assert pca.out_dim == 5  # rank <= N - 1
    path = tmp_path / "pca.pt"
    pca.save(path)
    back = PCAWhitening.load(path)
    assert torch.equal(back.transform(x), pca.transform(x)) and back.num_samples == 6
    with pytest.raises(ValueError, match="size 12"):
        pca.transform(torch.zeros(3, 7))


def test_online_pca_refit_schedule_and_freeze():
    x = _data(n=120)
    o = OnlinePCA(dim=4, whiten=True, shrinkage=0.0, min_samples=10, refit_growth=1.5, freeze_after=60)
    fits = []
    for i in range(len(x)):
        if o.update(x[i]):
            fits.append(i + 1)
    assert fits == [10, 15, 23, 35, 53, 60]  # geometric from min_samples, last fit at freeze_after
    assert o.version == len(fits) and o.n == 60
    ref = PCAWhitening.fit(x[:60], dim=4, whiten=True, shrinkage=0.0)  # same as a batch fit on what it saw
    assert torch.allclose(o.transform(x[100:]), ref.transform(x[100:]), atol=1e-4)
    assert torch.equal(OnlinePCA(min_samples=5).transform(x[:2]), x[:2].float())  # identity before the first fit


def test_index_reprojects_stored_descriptors_after_a_refit():
    x = _data(n=40).float()
    o = OnlinePCA(dim=6, min_samples=8, refit_growth=2.0)
    idx = KeyframeIndex(o)
    for i in range(40):
        o.update(x[i])
        idx.add(100 + i, x[i], float(i))
        d = idx.descriptors()
        # the cache always equals a fresh projection of all stored raw descriptors with the current transform
        fresh = o.transform(x[: i + 1])
        fresh = fresh / fresh.norm(dim=1, keepdim=True)
        assert torch.allclose(d, fresh, atol=1e-5), i
    assert torch.allclose(idx.descriptors().norm(dim=1), torch.ones(40), atol=1e-5)  # unit norm
    assert o.version == 3  # fits at 8, 16, 32


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def _route(seed: int = 0):
    """Descriptors of a trajectory that revisits places: keyframes 30..39 see the places of 5..14 again."""
    g = torch.Generator().manual_seed(seed)
    places = _unit(torch.randn(30, 64, generator=g))
    seq = list(range(30)) + list(range(5, 15))
    x = places[seq] + 0.05 * torch.randn(len(seq), 64, generator=g)  # revisit similarity ~0.86
    return x, seq


def _brute_force(x, times, q, threshold, exclude_recent, min_gap, max_c):
    xu = _unit(x)
    out = []
    for j in range(q - exclude_recent):
        s = float(xu[q] @ xu[j])
        if s >= threshold and times[q] - times[j] >= min_gap:
            out.append((s, j))
    return [j for s, j in sorted(out, reverse=True)[:max_c]]


@pytest.mark.parametrize("exclude_recent,min_gap", [(0, 0.0), (5, 0.0), (0, 12.0), (20, 3.0)])
def test_candidates_match_brute_force(exclude_recent, min_gap):
    x, seq = _route()
    times = [0.5 * i for i in range(len(seq))]
    idx = KeyframeIndex()
    ids = [1000 + 7 * i for i in range(len(seq))]  # arbitrary stable ids
    idx.add(ids, x, times)
    got = idx.candidates(ids, threshold=0.6, exclude_recent=exclude_recent, min_time_gap=min_gap, max_candidates=2)
    for q in range(len(seq)):
        ref = _brute_force(x, times, q, 0.6, exclude_recent, min_gap, 2)
        assert [ids.index(m.match) for m in got[q]] == ref, q
        assert all(m.query == ids[q] for m in got[q])
    # the revisits are found: keyframe 30 + r sees place 5 + r, i.e. keyframe 5 + r
    if exclude_recent == 0 and min_gap == 0.0:
        assert [ids.index(got[q][0].match) for q in range(30, 40)] == list(range(5, 15))
        assert all(got[q] == [] for q in range(30))  # no false positives on first visits


def test_temporal_exclusion_by_count_and_time():
    v = _unit(torch.ones(1, 8)).repeat(10, 1)  # all identical: only the exclusion decides
    idx = KeyframeIndex()
    idx.add(list(range(10)), v, [float(i) for i in range(10)])
    c = idx.candidates([9], threshold=0.5, exclude_recent=3, max_candidates=100)[0]
    assert sorted(m.match for m in c) == [0, 1, 2, 3, 4, 5]  # positions <= 9 - 1 - 3
    c = idx.candidates([9], threshold=0.5, min_time_gap=6.5, max_candidates=100)[0]
    assert sorted(m.match for m in c) == [0, 1, 2]  # at least 6.5 s older
    assert idx.candidates([0], threshold=-1.0, max_candidates=5) == [[]]  # nothing is older than the first


def test_removal_by_id_keeps_ids_stable():
    x, seq = _route()
    idx = KeyframeIndex()
    ids = [10 * i for i in range(len(seq))]
    idx.add(ids, x, [float(i) for i in range(len(seq))])
    idx.descriptors()  # fill the cache before removing
    idx.remove(70)  # keyframe at position 7 (place 7, revisited by position 32)
    assert 70 not in idx and len(idx) == len(seq) - 1 and idx.position(80) == 7
    c = idx.candidates([320, 330], threshold=0.6, max_candidates=1)
    assert c[0] == [] or c[0][0].match != 70  # place 7's only other view is gone
    assert c[1][0].match == 80  # ids, not positions, still name the right keyframe
    ref = _unit(torch.cat([x[:7], x[8:]]))
    assert torch.allclose(idx.descriptors(), ref, atol=1e-6)
    with pytest.raises(KeyError, match="keyframe id 70"):
        idx.remove(70)
    with pytest.raises(ValueError, match="already stored"):
        idx.add(80, x[0], 0.0)


def test_loop_retrieval_end_to_end_with_online_pca():
    x, seq = _route(seed=1)
    cfg = RetrievalConfig(threshold=0.6, exclude_recent=5, min_time_gap=0.0, max_candidates=1)
    r = LoopRetrieval(cfg, OnlinePCA(dim=None, whiten=False, min_samples=28))  # centring + rotation
    pairs = []
    for i in range(0, len(seq), 4):  # batches of 4 keyframes, ids = 2*i
        ids = [2 * k for k in range(i, min(i + 4, len(seq)))]
        r.add(ids, x[i : i + 4], [float(k) for k in range(i, i + 4)])
        pairs += [(m.query // 2, m.match // 2) for ms in r.candidates(ids) for m in ms]
    # every revisit is found, pointing at the right place; nothing else
    assert pairs == [(30 + r_, 5 + r_) for r_ in range(10)]
    assert len(r) == len(seq) and r.projector.version >= 1 and 2 * 31 in r
    r.remove(2 * 31)
    assert 2 * 31 not in r and len(r) == len(seq) - 1
