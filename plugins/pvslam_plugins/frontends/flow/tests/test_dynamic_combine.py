"""How the flow frontend combines a segmenter's movable segments with the geometric evidence.  With
``VOTE_KEEPS_CANDIDATES = False`` a movable thing segment is masked only when the residuals inside it say it moves
(a parked car stays static), pixels that cannot be judged neither vote for nor against, and isolated candidate
pixels outside voted segments are left to the robust kernel exactly as without a segmenter; the default (True)
is PVO's segm_filter, every raw candidate kept.  Checked against brute-force references written here, on a
hand-made residual field (a stub reprojection: the estimate maps every pixel onto itself)."""
import torch

from pvslam_core.slam.confidence import segment_vote
from pvslam_plugins.frontends.flow import dynamic as D
from pvslam_plugins.frontends.flow import dynamic_masking as masking_module

import pytest
import _flow_scenes as S

H, W = 12, 16
PARKED, MOVING, LEAVING, ROAD = 5, 6, 7, 1


def _scene():
    """Segment ids, residual field ``[H, W]`` (BA px) and validity of keyframe 0's edge to keyframe 1."""
    seg = torch.full((H, W), ROAD, dtype=torch.int64)
    seg[1:5, 1:6] = PARKED  # 20 px, residual 0 but for 2 noisy pixels
    seg[6:11, 8:13] = MOVING  # 25 px, 15 of them with a large residual
    seg[0:4, 10:16] = LEAVING  # 24 px, only 4 still in view, 3 of those with a large residual
    res = torch.zeros(H, W, dtype=torch.float64)
    res[1, 1] = res[4, 5] = 3.0  # flow noise on the parked car
    mov = torch.zeros(5, 5, dtype=torch.bool)
    mov.view(-1)[:15] = True  # the first three rows of the moving car
    res[6:11, 8:13][mov] = 3.0
    res[11, 0] = 3.0  # one isolated bad flow vector on the road
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[0:4, 10:16] = False
    valid[3, 12:16] = True  # the part of the leaving car still in view
    res[3, 12:15] = 3.0
    return seg, res, valid


@pytest.fixture
def combine(monkeypatch):
    """The rule with VOTE_KEEPS_CANDIDATES off."""
    monkeypatch.setattr(masking_module, "VOTE_KEEPS_CANDIDATES", False)


def _masking(**cfg):
    seg, res, valid = _scene()
    reproject, coords = S.identity_reproject(H, W, valid)  # the estimate maps each pixel onto itself
    things = [PARKED, MOVING, LEAVING]
    m = S.masking(H, W, {0: (seg, things), 1: (seg, things)}, reproject, **cfg)
    target = S.shifted_target(coords, res)[None]  # residual along u
    return m, target, seg, res, valid


def _reference(seg, res, valid, vote_thresh=0.5, keep_candidates=False):
    """Brute force: candidates (res > 1 BA px, the median being 0), regions of >= 4 px grown by 1, movable
    segments whose judged pixels are > vote_thresh candidates."""
    cand = (res > 1.0) & valid
    regions = D.group_regions(cand[None], 4, 1)[0]  # tested on its own in test_dynamic.py
    out = regions.clone()
    for sid in (PARKED, MOVING, LEAVING):
        m = seg == sid
        judged = [bool(cand[y, x]) for y in range(H) for x in range(W) if m[y, x] and valid[y, x]]
        if judged and sum(judged) / len(judged) > vote_thresh:
            out |= m
    if keep_candidates:
        out |= cand
    return out


def test_movable_segment_is_masked_only_when_its_geometry_moves(combine):
    m, target, seg, res, valid = _masking()
    dyn, frac, nvalid = m.masks(S.TwoKeyframeGraph(H, W), torch.tensor([0]), torch.tensor([1]), target)
    dyn = dyn[0].cpu()
    assert torch.equal(dyn, _reference(seg, res, valid))
    assert bool(dyn[seg == MOVING].all())  # 15 / 25 candidates: the whole car
    assert not bool(dyn[seg == PARKED].any())  # 2 / 20: a parked car stays static, noise included
    assert not bool(dyn[11, 0])  # the isolated road pixel is left to the robust kernel
    # 3 of its 4 judged pixels: the pixels that left the view do not count against it
    assert bool(dyn[seg == LEAVING].all())
    assert abs(frac[0] - float(dyn.float().mean())) < 1e-6 and nvalid[0] == int(valid.sum())


def test_keeping_the_candidates_is_pvos_segm_filter():
    assert masking_module.VOTE_KEEPS_CANDIDATES  # the default (docs/decisions.md: VOTE_KEEPS_CANDIDATES)
    m, target, seg, res, valid = _masking()
    dyn = m.masks(S.TwoKeyframeGraph(H, W), torch.tensor([0]), torch.tensor([1]), target)[0][0].cpu()
    # the old rule: every raw candidate, segments voted over all their pixels (the leaving car: 3 / 24, no vote)
    cand = (res > 1.0) & valid
    expected = D.group_regions(cand[None], 4, 1)[0] | cand | (seg == MOVING)
    assert torch.equal(dyn, expected)
    assert bool(dyn[11, 0]) and bool(dyn[1, 1]) and not bool(dyn[seg == PARKED].all())


def test_a_lower_vote_threshold_takes_a_partly_flagged_car(combine):
    m, target, seg, res, valid = _masking(vote_thresh=0.05)
    dyn = m.masks(S.TwoKeyframeGraph(H, W), torch.tensor([0]), torch.tensor([1]), target)[0][0].cpu()
    assert torch.equal(dyn, _reference(seg, res, valid, vote_thresh=0.05))
    assert bool(dyn[seg == PARKED].all())  # 2 / 20 = 0.1 > 0.05


def test_segment_vote_valid_and_keep_pixels_against_brute_force():
    g = torch.Generator().manual_seed(3)
    dyn = torch.rand(3, 9, 11, generator=g) > 0.6
    valid = torch.rand(3, 9, 11, generator=g) > 0.3
    seg = torch.randint(0, 6, (9, 11), generator=g)
    things = [2, 3, 5]
    for keep in (True, False):
        out = segment_vote(dyn, seg, thresh=0.4, thing_mask=things, valid=valid, keep_pixels=keep)
        for n in range(3):
            ref = dyn[n].clone() if keep else torch.zeros(9, 11, dtype=torch.bool)
            for sid in things:
                m = (seg == sid) & valid[n]
                if int(m.sum()) and float(dyn[n][m].float().mean()) > 0.4:
                    ref |= seg == sid
            assert torch.equal(out[n], ref)
    # without valid: every pixel counts (the behaviour before), and keep_pixels keeps the candidates
    out = segment_vote(dyn, seg, thresh=0.4, thing_mask=things)
    assert torch.equal(out, segment_vote(dyn, seg, thresh=0.4, thing_mask=things, valid=torch.ones_like(dyn)))
