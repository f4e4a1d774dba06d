"""``labels`` segmenter + ``warp_iou`` head on the synthetic ``moving_vehicles`` sequence: tracked ids must follow
the ground-truth instances (few id switches), with DIS flow and with the exact flow from depth + poses."""
from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import torch

from pvslam_core.interfaces import MotionCue
from pvslam_plugins.segmenters.labels.segmenter import LabelsSegmenter
from pvslam_plugins.vps.warp_iou.head import WarpIoUHead

generator = pytest.importorskip("pvslam_plugins.datasets.synthetic.generator")
reader = pytest.importorskip("pvslam_plugins.datasets.synthetic.reader")

NUM_FRAMES = 24
MIN_AREA = 150  # pixels: smaller (distant / entering) instances are not scored


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    root = generator.generate("moving_vehicles", tmp_path_factory.mktemp("mv") / "seq", num_frames=NUM_FRAMES,
                              progress=False)
    seq = reader.SyntheticSequence(root)
    return [seq.frame(i) for i in range(len(seq))]


def track(frames, head, cue_fn):
    seg = LabelsSegmenter()
    states, prev = [], None
    for t, fr in enumerate(frames):
        cue = cue_fn(frames, t) if t > 0 else MotionCue()
        prev = head.update(prev, fr, seg.segment(fr), cue)
        states.append(prev)
    return states


def id_switches(frames, states) -> tuple[int, int, int]:
    """(transitions scored, id switches, id merges): a switch = a GT instance's majority tracked id changes between
    consecutive frames; a merge = two GT instances of one frame share a tracked id."""
    switches = transitions = merges = 0
    last: dict[int, int] = {}
    for fr, st in zip(frames, states):
        gt = fr.gt_panoptic.ids.numpy()
        out = st.panoptic.ids.numpy()
        things = {s.id for s in fr.gt_panoptic.segments if s.isthing}
        cur: dict[int, int] = {}
        for g in things:
            m = gt == g
            if m.sum() < MIN_AREA:
                continue
            cur[g] = Counter(out[m].tolist()).most_common(1)[0][0]
        merges += len(cur) - len(set(cur.values()))
        for g, tid in cur.items():
            if g in last:
                transitions += 1
                switches += tid != last[g]
        last = cur
    return transitions, switches, merges


def rigid_cue(frames, t):
    p, c = frames[t - 1], frames[t]
    return MotionCue(depth_prev=p.gt_depth, pose_prev=p.gt_pose, pose_cur=c.gt_pose,
                     intrinsics=p.intrinsics.vector())


@pytest.mark.slow
def test_tracked_ids_follow_ground_truth_instances_with_dis(frames):
    states = track(frames, WarpIoUHead(), lambda fr, t: MotionCue())
    n, sw, merges = id_switches(frames, states)
    assert n >= 20, "the scenario should show several vehicles"
    assert sw <= max(1, n // 20), (n, sw)
    assert merges == 0
    for st in states:
        ids = set(torch.unique(st.panoptic.ids).tolist()) - {0}
        assert ids == {s.id for s in st.panoptic.segments}


@pytest.mark.slow
def test_tracked_ids_with_depth_cue(frames):
    # depth + poses only (no flow): DIS for things, the rigid warp for stuff, z-ordered by depth
    states = track(frames, WarpIoUHead(), rigid_cue)
    n, sw, merges = id_switches(frames, states)
    assert sw <= max(1, n // 20), (n, sw)
    assert merges == 0
