"""Places of the loop policy (pvslam_core.slam.loops, rule 3): on repeated laps a place is closed once per
revisit, not once per earlier lap."""
import torch

import pvslam_core.slam.loops as loops
from pvslam_core.config import LoopClosureSection
from pvslam_core.slam.graph import FrameGraph
from pvslam_core.slam.loops import LoopPolicy, UnionFind
from pvslam_core.types import LoopCandidate

LAP = 30  # keyframes per lap: keyframe k sees the same place as k - LAP, k - 2 LAP, ...


def laps_graph(n: int) -> FrameGraph:
    g = FrameGraph(3, 4, torch.tensor([4.0, 4.0, 1.5, 1.0]))
    for k in range(n):
        pose = torch.tensor([0.1 * k, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64)  # same orientation everywhere
        g.add_keyframe(10 * k, float(k), pose, torch.ones(3, 4))
    return g


def drive(laps: int, nms: int = 3) -> list[tuple[int, int]]:
    """Each keyframe of laps 2.. proposes the same place on every earlier lap (oldest lap first, as a detector
    with equal scores would); returns the accepted closures (i, j)."""
    g = laps_graph(laps * LAP)
    old = loops.NMS_KEYFRAMES, loops.LOOP_BA_MIN_GAP
    loops.NMS_KEYFRAMES, loops.LOOP_BA_MIN_GAP = nms, 0
    try:
        p = LoopPolicy(LoopClosureSection(), g)
        for k in range(LAP, laps * LAP):
            cands = [LoopCandidate(k, k - m * LAP, 0.9, True) for m in range(k // LAP, 0, -1)]
            d = p.decide(cands)
            if d is not None:
                p.accepted(d)
    finally:
        loops.NMS_KEYFRAMES, loops.LOOP_BA_MIN_GAP = old
    return [(c.kf_i, c.kf_j) for c in p.closures]


def per_lap(closures: list[tuple[int, int]], laps: int) -> list[int]:
    return [sum(1 for i, _ in closures if lap * LAP <= i < (lap + 1) * LAP) for lap in range(1, laps)]


def test_union_find_against_brute_force_components():
    pairs = [(0, 5), (5, 9), (20, 21), (9, 2), (30, 31), (31, 20)]
    uf = UnionFind()
    for a, b in pairs:
        uf.union(a, b)
    nodes = sorted({x for p in pairs for x in p})
    # brute force: grow components by repeated merging of overlapping sets
    comps = [{a, b} for a, b in pairs]
    merged = True
    while merged:
        merged = False
        for x in range(len(comps)):
            for y in range(x + 1, len(comps)):
                if comps[x] & comps[y]:
                    comps[x] |= comps.pop(y)
                    merged = True
                    break
            if merged:
                break
    for a in nodes:
        for b in nodes:
            same = any(a in c and b in c for c in comps)
            assert (uf.find(a) == uf.find(b)) == same, (a, b)
    assert uf.size[uf.find(20)] == 4


def test_later_laps_do_not_reclose_each_earlier_lap(monkeypatch):
    laps = 5
    recent = loops.PLACE_RECENT
    with_places = drive(laps)
    monkeypatch.setattr(loops, "PLACE_RECENT", 0)  # the plain index rule only
    plain = drive(laps)
    n_places, n_plain = per_lap(with_places, laps), per_lap(plain, laps)
    # the plain rule closes each place again to each earlier lap: more closures on every later lap
    assert n_plain[-1] > n_plain[0]
    # with places, later laps close no more often than the first revisit
    assert all(n <= n_places[0] for n in n_places[1:]), n_places
    assert sum(n_places) < 0.75 * sum(n_plain), (n_places, n_plain)
    # and every lap still closes regularly: no stretch of more than PLACE_RECENT * nms + 2 keyframes without one
    for lap in range(1, laps):
        ii = sorted(i for i, _ in with_places if lap * LAP <= i < (lap + 1) * LAP)
        gaps = [b - a for a, b in zip([lap * LAP] + ii, ii + [(lap + 1) * LAP - 1])]
        assert max(gaps) <= recent * 3 + 2, (lap, ii)


def test_first_revisit_unchanged():
    """A place seen only twice keeps the plain rule (the first revisit needs its closures)."""
    laps = 2
    import pvslam_core.slam.loops as mod

    with_places = drive(laps)
    old = mod.PLACE_RECENT
    try:
        mod.PLACE_RECENT = 0
        plain = drive(laps)
    finally:
        mod.PLACE_RECENT = old
    assert with_places == plain



def test_newest_lap_is_closed_first():
    """Rule 5: of several acceptable candidates the most recent lap's wins, whatever the detector's order or score:
    the loop BA's pose graph then bends one lap, not all those in between."""
    g = laps_graph(3 * LAP)
    p = LoopPolicy(LoopClosureSection(), g)
    k = 2 * LAP + 7
    d = p.decide([LoopCandidate(k, 7, 0.99, True), LoopCandidate(k, LAP + 7, 0.80, True)])
    assert d.closure.kf_j == LAP + 7
    # a newer candidate that fails a rule does not block the older one
    p2 = LoopPolicy(LoopClosureSection(), g)
    d2 = p2.decide([LoopCandidate(k, 7, 0.99, True), LoopCandidate(k, LAP + 7, 0.80, False)])
    assert d2.closure.kf_j == 7
    # within the most recent visit the detector's order (best first) stands
    p3 = LoopPolicy(LoopClosureSection(), g)
    d3 = p3.decide([LoopCandidate(k, 5, 0.99, True), LoopCandidate(k, LAP + 5, 0.95, True),
                    LoopCandidate(k, LAP + 8, 0.90, True)])
    assert d3.closure.kf_j == LAP + 5
