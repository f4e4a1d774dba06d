"""PV-SLAM eq. 4 (panoptic-aware confidence) in both mask conventions, and segment voting."""
import math

import pytest
import torch

from pvslam_core.slam.confidence import logit, observed_flow_weight, panoptic_aware_weight, segment_vote


def _sig(x):
    return 1.0 / (1.0 + math.exp(-x))


@pytest.mark.parametrize("w", [-3.0, 0.0, 2.5])
def test_eq4_values_paper_convention(w):
    wl = torch.tensor([w, w])
    m_d = torch.tensor([0.0, 1.0])  # static, dynamic
    out = panoptic_aware_weight(wl, m_d, offset=10.0)
    assert float(out[0]) == pytest.approx(_sig(w + 10.0), rel=1e-6)  # static: + eta
    assert float(out[1]) == pytest.approx(_sig(w), rel=1e-6)  # dynamic: raw logit
    # soft masks interpolate the logit offset linearly
    half = panoptic_aware_weight(torch.tensor(w), torch.tensor(0.5), offset=10.0)
    assert float(half) == pytest.approx(_sig(w + 5.0), rel=1e-6)


@pytest.mark.parametrize("w", [-3.0, 0.0, 2.5])
def test_eq4_values_pvo_code_convention(w):
    wl = torch.tensor([w, w])
    m_d = torch.tensor([0.0, 1.0])  # still pvslam's mask: 1 = dynamic
    out = panoptic_aware_weight(wl, m_d, offset=10.0, convention="pvo_code")
    # PVO's code: sigmoid(w + (1 - M_s) * 10) with M_s = 1 on static pixels
    assert float(out[0]) == pytest.approx(_sig(w), rel=1e-6)  # static: raw logit
    assert float(out[1]) == pytest.approx(_sig(w + 10.0), rel=1e-6)  # dynamic: + eta
    with pytest.raises(ValueError):
        panoptic_aware_weight(wl, m_d, convention="other")


def test_bool_mask_and_broadcast():
    wl = torch.zeros(2, 3, 4)
    dyn = torch.zeros(3, 4, dtype=torch.bool)
    dyn[1, 2] = True
    out = panoptic_aware_weight(wl, dyn, offset=4.0)
    assert out.shape == (2, 3, 4)
    assert float(out[0, 1, 2]) == pytest.approx(0.5)
    assert float(out[1, 0, 0]) == pytest.approx(_sig(4.0))


def test_observed_flow_weight_classical_frontend():
    c = torch.tensor([0.01, 0.3, 0.8, 0.99, 1.0])
    static = observed_flow_weight(c, torch.zeros(5))
    dynamic = observed_flow_weight(c, torch.ones(5))
    torch.testing.assert_close(static, c.clamp(max=0.99), atol=1e-5, rtol=1e-5)  # static -> c
    # dynamic -> sigmoid(logit(c) - eta) ~ c e^-eta for small c, bounded for c -> 1
    assert float(dynamic[0]) == pytest.approx(0.01 * math.exp(-10), rel=0.02)
    assert (dynamic <= 0.0046).all() and (dynamic < static * 0.005).all()
    assert observed_flow_weight(c, None) is c
    # the PVO-code convention reverses it: dynamic pixels keep their confidence
    pvo_dyn = observed_flow_weight(c, torch.ones(5), convention="pvo_code")
    torch.testing.assert_close(pvo_dyn, c.clamp(max=0.99), atol=1e-5, rtol=1e-5)


def test_logit_finite():
    x = logit(torch.tensor([0.0, 0.5, 1.0]))
    assert torch.isfinite(x).all() and float(x[1]) == 0.0


def _seg():
    ids = torch.zeros(6, 8, dtype=torch.int64)
    ids[:, :4] = 7000  # stuff (e.g. building)
    ids[:3, 4:] = 26001  # car 1
    ids[3:, 4:] = 26002  # car 2
    ids[0, 0] = 0  # void
    return ids


def test_segment_vote_marks_whole_segment():
    ids = _seg()
    dyn = torch.zeros(6, 8)
    dyn[:2, 4:] = 0.9  # 8 of the 12 pixels of car 1
    dyn[3, 4] = 1.0  # 1 of 12 pixels of car 2
    dyn[0, 1] = 1.0  # a stuff pixel
    out = segment_vote(dyn, ids, thresh=0.5)
    assert out.dtype == torch.bool and out.shape == (6, 8)
    assert out[:3, 4:].all()  # car 1 voted dynamic as a whole
    assert out[3:, 4:].sum() == 1  # car 2 keeps its one pixel (no vote)
    assert out[0, 1] and out[:, :4].sum() == 1  # stuff: 1 of 23 pixels, no vote, pixel kept
    # higher threshold: car 1 (8/12 = 0.67) no longer votes
    assert segment_vote(dyn, ids, thresh=0.7)[:3, 4:].sum() == 8


def test_segment_vote_things_only_and_void():
    ids = _seg()
    dyn = torch.zeros(6, 8, dtype=torch.bool)
    dyn[:, :3] = True  # most of the stuff segment (and the void pixel)
    dyn[:3, 4:6] = True
    dyn[0, 6] = True  # car 1: 7 / 12
    voted = segment_vote(dyn, ids)
    assert voted[:, :4][ids[:, :4] != 0].all()  # stuff votes when no thing mask is given
    assert not voted[0, 0] or dyn[0, 0]  # void never becomes dynamic by a vote
    for things in ([26001, 26002], torch.tensor([26001, 26002]),
                   torch.zeros(30000, dtype=torch.bool).index_fill_(0, torch.tensor([26001, 26002]), True)):
        out = segment_vote(dyn, ids, thing_mask=things)
        assert out[:3, 4:].all()  # the car votes
        assert out[:, 3].sum() == 0  # the stuff segment does not; its column 3 stays static
        assert out[:, :3].all()  # per-pixel flags are kept
    ids2 = ids.clone()
    ids2[:, :4] = 0  # all void
    assert segment_vote(dyn, ids2)[:, 3].sum() == 0


def test_segment_vote_batched_edges():
    ids = _seg()
    dyn = torch.zeros(3, 6, 8)
    dyn[0, :2, 4:] = 1  # edge 0: car 1 mostly dynamic
    dyn[1, 3:5, 4:] = 1  # edge 1: car 2 mostly dynamic
    out = segment_vote(dyn, ids)
    assert out[0, :3, 4:].all() and out[0, 3:, 4:].sum() == 0
    assert out[1, 3:, 4:].all() and out[1, :3, 4:].sum() == 0
    assert out[2].sum() == 0
    # one id map per edge
    ids_b = torch.stack([ids, ids.flip(1), ids])
    out_b = segment_vote(dyn, ids_b)
    assert out_b.shape == (3, 6, 8)
    assert out_b[0, :3, 4:].all()
    with pytest.raises(ValueError):
        segment_vote(dyn, ids[:4])


def test_segment_vote_batch_matches_brute_force():
    """The vectorised vote over many edges and segments equals a per-edge, per-segment Python loop."""
    g = torch.Generator().manual_seed(3)
    ids = torch.randint(1, 40, (30, 40), generator=g) * 1000
    ids[:3] = 0  # void never votes
    dyn = torch.rand(16, 30, 40, generator=g) ** 3  # mostly static, some segments dynamic
    things = [k * 1000 for k in range(1, 40, 2)]
    out = segment_vote(dyn, ids, thresh=0.3137, thing_mask=things)  # (a threshold no count ratio hits exactly)
    ref = dyn > 0.5
    for e in range(dyn.shape[0]):
        for sid in torch.unique(ids).tolist():
            if sid == 0 or sid not in things:
                continue
            m = ids == sid
            if float((dyn[e][m] > 0.5).sum()) / float(m.sum()) > 0.3137:
                ref[e][m] = True
    assert torch.equal(out, ref) and bool(out.any()) and not bool(out.all())


def test_per_id_map_things_against_brute_force():
    """``batch_things``: each id map votes with its own movable ids (ids are unique only within one frame), checked
    per pixel against a brute-force vote; pooling the ids into one ``thing_mask`` lets another map's ids vote."""
    g = torch.Generator().manual_seed(5)
    seg = torch.randint(0, 7, (3, 6, 8), generator=g)
    dyn = torch.rand(3, 6, 8, generator=g) > 0.55
    things = [torch.tensor([1, 3]), None, torch.tensor([6, 2, 0])]
    out = segment_vote(dyn, seg, thresh=0.4, batch_things=things)
    ref = dyn.clone()
    for n, t in enumerate(things):
        for sid in (set(t.tolist()) if t is not None else set()) - {0}:  # void never votes
            m = seg[n] == sid
            if int(m.sum()) and float(dyn[n][m].sum()) / float(m.sum()) > 0.4:
                ref[n][m] = True
    assert torch.equal(out, ref) and not torch.equal(out, dyn)
    pooled = segment_vote(dyn, seg, thresh=0.4, thing_mask=torch.tensor([1, 2, 3, 6]))
    assert not torch.equal(pooled, out)  # the pooled ids vote segments their own map does not call movable
    with pytest.raises(ValueError, match="batch_things has 2 entries for 3 id maps"):
        segment_vote(dyn, seg, batch_things=things[:2])
