"""Tests of the oracle ``labels`` segmenter."""
from __future__ import annotations

import pytest
import torch

from pvslam_core.types import Frame, Intrinsics, PanopticSegmentation, Segment
from pvslam_plugins.segmenters.labels.segmenter import (
    LabelsSegmenter,
    LabelsSegmenterConfig,
    MissingPanopticLabels,
    make_segmenter,
)

W, H = 16, 12
K = Intrinsics(fx=14.0, fy=14.0, cx=7.5, cy=5.5, width=W, height=H)
ROAD, CAR, PERSON = 1, 3, 5


def gt() -> PanopticSegmentation:
    ids = torch.full((H, W), ROAD * 1000, dtype=torch.int64)
    ids[:3] = 0  # void
    ids[4:8, 1:5] = CAR * 1000 + 1
    ids[4:8, 8:12] = CAR * 1000 + 2
    ids[9:11, 13:15] = PERSON * 1000 + 7
    segs = [Segment(ROAD * 1000, ROAD, False), Segment(CAR * 1000 + 1, CAR, True),
            Segment(CAR * 1000 + 2, CAR, True), Segment(PERSON * 1000 + 7, PERSON, True)]
    return PanopticSegmentation(ids, segs)


def frame(panoptic=None, index=3, name="000003.png") -> Frame:
    return Frame(index=index, timestamp=0.3, image=torch.zeros(3, H, W, dtype=torch.uint8), intrinsics=K,
                 gt_panoptic=panoptic, name=name)


def test_returns_ground_truth_copy():
    g = gt()
    out = LabelsSegmenter().segment(frame(g))
    assert torch.equal(out.ids, g.ids) and out.ids.dtype == torch.int64
    assert [(s.id, s.category_id, s.isthing, s.score) for s in out.segments] == \
        [(s.id, s.category_id, s.isthing, 1.0) for s in g.segments]
    out.ids[0, 0] = 99  # the dataset's labels are not modified through the result
    assert g.ids[0, 0] == 0


def test_score_option():
    out = LabelsSegmenter(LabelsSegmenterConfig(score=0.7)).segment(frame(gt()))
    assert all(s.score == pytest.approx(0.7) for s in out.segments)


def test_drop_instances_merges_things_per_category():
    out = LabelsSegmenter(LabelsSegmenterConfig(drop_instances=True)).segment(frame(gt()))
    ids = set(torch.unique(out.ids).tolist())
    assert ids == {0, ROAD * 1000, CAR * 1000, PERSON * 1000}
    assert {s.id for s in out.segments} == ids - {0}
    assert int(out.ids[5, 2]) == int(out.ids[5, 9]) == CAR * 1000
    car = out.segment(CAR * 1000)
    assert car is not None and car.isthing and car.category_id == CAR
    assert torch.equal(out.category_map(), gt().category_map())


def test_missing_labels_error_names_frame():
    with pytest.raises(MissingPanopticLabels) as exc:
        LabelsSegmenter().segment(frame(None, index=17, name="img_17.png"))
    msg = str(exc.value)
    assert "frame 17" in msg and "img_17.png" in msg and "panoptic ground truth" in msg
    assert "segmenter.plugin = 'none'" in msg


def test_resized_labels_follow_the_image():
    g = gt()
    big = PanopticSegmentation(g.ids.repeat_interleave(2, 0).repeat_interleave(2, 1), g.segments)
    out = LabelsSegmenter().segment(frame(big))
    assert out.ids.shape == (H, W) and torch.equal(out.ids, g.ids)


def test_registered_hook_and_config():
    import pvslam_plugins.segmenters.labels as plugin

    got = []
    plugin.register_segmenters(register=lambda name, factory, model, description="", **extras: got.append(
        (name, factory, model, extras)))
    name, factory, model, extras = got[0]
    assert name == "labels" and isinstance(factory(model(), None), LabelsSegmenter)
    assert extras == {"needs_gt_panoptic": True}  # the core switches it off on data without panoptic labels
    assert isinstance(make_segmenter(LabelsSegmenterConfig(), None), LabelsSegmenter)
    with pytest.raises(Exception):
        model(drop_instance=True)  # typo -> error
