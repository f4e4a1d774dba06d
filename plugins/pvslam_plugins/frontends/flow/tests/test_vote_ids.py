"""Segment ids are unique only within one frame.  A learned segmenter numbers its segments 1, 2, ... in
every frame, so the id of a car in one keyframe is the id of the road in another; the segment vote of a batch of
edges must use each source keyframe's own movable ids.  Before the fix the union of the edges' thing ids was used,
and a road flagged by flow errors on more than half its pixels was voted "dynamic" whole.  Checked against a
brute-force per-pixel reference written here."""
import torch

from pvslam_plugins.frontends.flow import dynamic_masking as masking_module
import _flow_scenes as S

H, W = 10, 12


def _scene():
    """Keyframe 0: road = id 4 (stuff) over the lower half, a car id 1; keyframe 1: cars 1..5 (id 4 a car)."""
    seg0 = torch.full((H, W), 2, dtype=torch.int64)  # id 2: building (stuff) in keyframe 0
    seg0[5:, :] = 4  # the road
    seg0[1:4, 1:4] = 1  # a car
    seg1 = torch.zeros(H, W, dtype=torch.int64)
    for k in range(1, 6):
        seg1[:, 2 * k: 2 * k + 2] = k  # five cars in columns
    res = torch.zeros(H, W, dtype=torch.float64)
    res[5:, :][torch.arange(5 * W).reshape(5, W) % 3 != 0] = 3.0  # two thirds of the road flagged (flow errors)
    res[1:3, 1:4] = 3.0  # 6 of the car's 9 pixels
    return seg0, seg1, res


def _masking():
    seg0, seg1, res = _scene()
    reproject, coords = S.identity_reproject(H, W)
    m = S.masking(H, W, {0: (seg0, [1]), 1: (seg1, [1, 2, 3, 4, 5])}, reproject, max_fraction=1.0)
    tgt = S.shifted_target(coords, res)
    return m, torch.stack([tgt, tgt]), (seg0, seg1), res


def _reference(seg, things, res, thresh=0.5):
    """Per pixel: a candidate (residual > 1 BA px), or in a segment of this keyframe's own movable ids with more
    than ``thresh`` of its pixels candidates."""
    cand = res > 1.0
    out = cand.clone()
    for sid in things:
        m = seg == sid
        n = int(m.sum())
        if n and sum(bool(cand[y, x]) for y in range(H) for x in range(W) if m[y, x]) / n > thresh:
            out |= m
    return out


def test_each_source_votes_with_its_own_movable_ids(monkeypatch):
    # without regions the rule is "candidates OR voted segments": what the vote adds is visible on its own
    monkeypatch.setattr(masking_module, "DYNAMIC_REGIONS", False)
    m, target, (seg0, seg1), res = _masking()
    dyn = m.masks(S.TwoKeyframeGraph(H, W), torch.tensor([0, 1]), torch.tensor([1, 0]), target)[0].cpu()
    assert torch.equal(dyn[0], _reference(seg0, [1], res))
    assert torch.equal(dyn[1], _reference(seg1, [1, 2, 3, 4, 5], res))
    road = seg0 == 4
    assert not bool(dyn[0][road].all())  # keyframe 1's car id 4 does not make keyframe 0's road movable
    assert int(dyn[0][road].sum()) == int((res[road] > 1).sum())  # only its own candidates
    assert bool(dyn[0][seg0 == 1].all())  # the car (6 / 9) is voted whole
