"""The ``panoptic_fpn`` segmenter plugin: registration, config errors, on-demand segmentation, empty frames,
movable flags (and the frontend's vote reading them), core-typed features."""
from __future__ import annotations

import pytest
import torch
from pydantic import ValidationError

from pvslam_core.registry import get_registry
from pvslam_core.training import find_trainer
from pvslam_core.types import FeaturePyramid, Frame, Intrinsics, PanopticSegmentation, Segment
from pvslam_core.weights import WeightsError
from pvslam_plugins.segmenters.panoptic_fpn.checkpoint import save_checkpoint
from pvslam_plugins.segmenters.panoptic_fpn.config import reduced
from pvslam_plugins.segmenters.panoptic_fpn.data import synthetic_category_set
from pvslam_plugins.segmenters.panoptic_fpn.model import PanopticFPN
from pvslam_plugins.segmenters.panoptic_fpn.segmenter import (
    DeferredPanoptic,
    PanopticFPNSegmenter,
    PanopticFPNSegmenterConfig,
    build_model,
    make_segmenter,
)

H, W = 48, 64
CAR, TRUCK = 11, 12  # synthetic category ids


def frame(seed: int = 0, index: int = 0) -> Frame:
    img = (torch.rand(3, H, W, generator=torch.Generator().manual_seed(seed)) * 255).to(torch.uint8)
    return Frame(index=index, timestamp=0.1 * index, image=img,
                 intrinsics=Intrinsics(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=W, height=H))


@pytest.fixture
def tiny_weights(tmp_path):
    """A randomly initialised reduced model in pvslam's checkpoint format."""
    torch.manual_seed(0)
    path = tmp_path / "tiny.pth"
    save_checkpoint(PanopticFPN(reduced(), synthetic_category_set()), path)
    return str(path)


@pytest.fixture
def forced_weights(tmp_path):
    """Heads forced to: semantic channel of 'road' everywhere, class 'car' with score ~1 and full masks for every
    proposal (the thing boxes come from the RPN anchors)."""
    torch.manual_seed(0)
    cats = synthetic_category_set()
    model = PanopticFPN(reduced(), cats)
    road = cats.semantic_ids().tolist().index(1)
    with torch.no_grad():
        sem = model.sem_seg_head.predictor
        sem.weight.zero_()
        sem.bias.zero_()
        sem.bias[road] = 10.0
        cls = model.roi_heads.box_predictor.cls_score
        cls.weight.zero_()
        cls.bias.zero_()
        cls.bias[0] = 20.0  # contiguous class 0 = car
        model.roi_heads.box_predictor.bbox_pred.weight.zero_()
        model.roi_heads.box_predictor.bbox_pred.bias.zero_()
        model.roi_heads.mask_head.predictor.weight.zero_()
        model.roi_heads.mask_head.predictor.bias.fill_(10.0)
    path = tmp_path / "forced.pth"
    save_checkpoint(model, path)
    return str(path)


def test_registered_with_trainer_and_config_defaults():
    spec = get_registry().get("segmenter", "panoptic_fpn")
    assert spec.config_model is PanopticFPNSegmenterConfig and spec.entry_point == "panoptic_fpn"
    assert not spec.extras.get("needs_gt_panoptic") and "auto_ready" not in spec.extras
    trainer = find_trainer("segmenter", "panoptic_fpn")
    assert trainer.config_model.__name__ == "TrainConfig"
    cfg = PanopticFPNSegmenterConfig()
    assert (cfg.preset, cfg.weights, cfg.frames, cfg.movable) == ("reduced", None, "on_demand", None)


def test_config_errors(tmp_path, tiny_weights):
    with pytest.raises(ValidationError, match="weigths"):
        PanopticFPNSegmenterConfig(weigths="x.pth")
    with pytest.raises(ValidationError, match="preset"):
        PanopticFPNSegmenterConfig(preset="r101")
    with pytest.raises(ValidationError, match="frames"):
        PanopticFPNSegmenterConfig(frames="keyframes")
    with pytest.raises(WeightsError, match="no such file"):
        build_model(PanopticFPNSegmenterConfig(weights=str(tmp_path / "missing.pth")))
    with pytest.raises(ValueError, match=r"no categories named \['bicycle'\]"):
        build_model(PanopticFPNSegmenterConfig(weights=tiny_weights, movable=["car", "bicycle"]))
    with pytest.raises(ValueError, match=r"\['road'\] are stuff categories"):
        build_model(PanopticFPNSegmenterConfig(weights=tiny_weights, movable=["road"]))
    with pytest.raises(ValueError, match="set segmenter.preset to match the file"):
        build_model(PanopticFPNSegmenterConfig(preset="coco_r50", weights=tiny_weights))


def test_on_demand_segments_when_read(tiny_weights):
    seg = make_segmenter(PanopticFPNSegmenterConfig(weights=tiny_weights, features=False))
    out = seg.segment(frame())
    assert isinstance(out, DeferredPanoptic) and isinstance(out, PanopticSegmentation) and not out.computed
    assert seg.stats["frames_segmented"] == 0
    ids = out.ids  # first read runs the network
    assert out.computed and seg.stats["frames_segmented"] == 1
    assert ids.shape == (H, W) and ids.dtype == torch.int64 and out.features is None
    assert {int(i) for i in ids.unique()} - {0} == {s.id for s in out.segments}
    eager = PanopticFPNSegmenter(PanopticFPNSegmenterConfig(weights=tiny_weights, frames="all", features=False),
                                 model=seg.model)
    again = eager.segment(frame())
    assert type(again) is PanopticSegmentation and torch.equal(again.ids, ids)
    assert again.segments == out.segments


def test_reading_only_features_runs_no_heads(tiny_weights):
    """A feature-level VPS head reads only ``features``: the heads must not run for it, and a later read of the
    segmentation decodes the same pyramid (equal to the eager result)."""
    seg = make_segmenter(PanopticFPNSegmenterConfig(weights=tiny_weights))
    out = seg.segment(frame())
    feats = out.features
    assert set(feats.maps) == {"p2", "p3", "p4", "p5", "p6"} and seg.stats["frames_segmented"] == 0
    assert not out.computed and "features only" in repr(out)
    ids = out.ids
    assert out.computed and seg.stats["frames_segmented"] == 1
    eager = PanopticFPNSegmenter(PanopticFPNSegmenterConfig(weights=tiny_weights, frames="all"), model=seg.model)
    again = eager.segment(frame())
    assert torch.equal(again.ids, ids) and again.segments == out.segments
    for k in feats.maps:
        assert torch.equal(feats.maps[k], again.features.maps[k]) and torch.equal(out.features.maps[k], feats.maps[k])


def test_empty_frame_gives_void_and_no_segments(tiny_weights):
    cfg = PanopticFPNSegmenterConfig(weights=tiny_weights, instances_confidence_thresh=1.0,
                                     stuff_area_limit=10 ** 9, frames="all")
    seg = make_segmenter(cfg)
    out = seg.segment(frame())
    assert out.segments == [] and not out.ids.any() and seg.stats["empty_frames"] == 1
    assert out.category_map().eq(-1).all()


def test_movable_flags_follow_the_list(forced_weights):
    default = make_segmenter(PanopticFPNSegmenterConfig(weights=forced_weights, frames="all"))
    out = default.segment(frame())
    things = [s for s in out.segments if s.isthing]
    stuff = [s for s in out.segments if not s.isthing]
    assert things and all(s.category_id == CAR and s.movable for s in things)  # synthetic set: car, truck movable
    assert stuff and all(s.category_id == 1 and not s.movable for s in stuff)
    trucks_only = make_segmenter(PanopticFPNSegmenterConfig(weights=forced_weights, frames="all", movable=["Truck"]))
    out2 = trucks_only.segment(frame())
    assert [s.id for s in out2.segments] == [s.id for s in out.segments]
    assert not any(s.movable for s in out2.segments)
    assert trucks_only.model.categories.movable == frozenset({TRUCK})
    assert [c.name for c in default.categories()] == [c.name for c in synthetic_category_set().categories]


def test_frontend_vote_uses_movable_things_only():
    """The flow frontend's segment vote: a thing that cannot move never becomes dynamic as a whole."""
    from pvslam_core.slam.confidence import segment_vote
    from pvslam_plugins.frontends.flow.frontend import FlowFrontend

    ids = torch.zeros(8, 8, dtype=torch.int64)
    ids[:, :4] = 11001  # a car
    ids[:, 4:] = 13001  # furniture, not movable
    seg = PanopticSegmentation(ids, [Segment(11001, CAR, True), Segment(13001, 13, True, movable=False)])
    seg_ba, things = FlowFrontend._seg_info(None, seg, 8, 8)
    assert things.tolist() == [11001]
    dyn = torch.zeros(8, 8, dtype=torch.bool)
    dyn[:7] = True  # 7/8 of each segment moves
    voted = segment_vote(dyn, seg_ba, thresh=0.5, thing_mask=things)
    assert voted[:, :4].all() and not voted[7, 4:].any()


def test_features_are_the_core_pyramid(tiny_weights):
    seg = make_segmenter(PanopticFPNSegmenterConfig(weights=tiny_weights, frames="all"))
    f = seg.segment(frame()).features
    assert isinstance(f, FeaturePyramid) and f.names == ["p2", "p3", "p4", "p5", "p6"]
    for name in f.names:
        s = f.strides[name]
        assert f.maps[name].shape == (64, -(-H // 32) * 32 // s, W // s)  # padded to 32, 64 channels (reduced)
