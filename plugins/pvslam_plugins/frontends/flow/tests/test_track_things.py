"""The tracking weights take out the reference keyframe's movable thing segments whether or not the geometry has
judged them (``dynamic_masking.TRACK_THINGS``): a vehicle that grows to fill the view must not drag the tracked pose
before its own masks exist.  Stuff and things that cannot move keep their weights; without a segmentation nothing
changes."""
import pytest
import torch

from pvslam_core.slam.confidence import observed_flow_weight
from pvslam_core.slam.dynamic_config import DynamicMaskingConfig
from pvslam_core.types import PanopticSegmentation, Segment
from pvslam_plugins.frontends.flow import dynamic_masking as masking_module
from pvslam_plugins.frontends.flow.dynamic_masking import DynamicMasking

import _flow_scenes as S

H, W = 12, 16
CAR, BUILDING, SIGN = 1, 2, 3  # a movable thing, stuff, a thing that cannot move


def _seg() -> PanopticSegmentation:
    ids = torch.full((H, W), BUILDING, dtype=torch.int64)
    ids[6:, 2:8] = CAR
    ids[1:4, 10:12] = SIGN
    return PanopticSegmentation(ids=ids, segments=[
        Segment(id=CAR, category_id=5, isthing=True), Segment(id=BUILDING, category_id=1, isthing=False),
        Segment(id=SIGN, category_id=7, isthing=True, movable=False)])


def _tracked(seg, geometric=None, on=True, monkeypatch=None):
    """Weights ``[2, H, W]`` (all 1 before) of a frame tracked against keyframe 0 with segmentation ``seg`` and the
    keyframe mask ``geometric`` (None: not judged, nothing moved from a reference)."""
    monkeypatch.setattr(masking_module, "TRACK_THINGS", on)
    m = DynamicMasking(DynamicMaskingConfig(), S.identity_reproject(H, W)[0])
    m.add_keyframe(0, seg, H, W)
    if geometric is not None:
        m.keyframe(0).dyn, m.keyframe(0).dyn_judged = geometric.float(), True
    w = torch.ones(2, H, W)
    m.track_weights(0, w, None)
    return w


def _car() -> torch.Tensor:
    car = torch.zeros(H, W, dtype=torch.bool)
    car[6:, 2:8] = True
    return car


def test_a_movable_thing_is_taken_out_of_the_tracking_before_any_judgement(monkeypatch):
    w = _tracked(_seg(), monkeypatch=monkeypatch)
    low = float(observed_flow_weight(torch.tensor(1.0), torch.tensor(1.0)))  # eq. 4 on a dynamic pixel
    car = _car()
    assert torch.allclose(w[:, car], torch.full_like(w[:, car], low))
    assert torch.equal(w[:, ~car], torch.ones_like(w[:, ~car]))  # the building and the sign keep their weights


def test_the_geometric_mask_and_the_things_add_up(monkeypatch):
    moving = torch.zeros(H, W, dtype=torch.bool)
    moving[0:3, 0:4] = True  # a region the geometry found moving, outside every movable segment
    w = _tracked(_seg(), geometric=moving, monkeypatch=monkeypatch)
    low = float(observed_flow_weight(torch.tensor(1.0), torch.tensor(1.0)))
    both = moving | _car()
    assert torch.allclose(w[:, both], torch.full_like(w[:, both], low))
    assert torch.equal(w[:, ~both], torch.ones_like(w[:, ~both]))


@pytest.mark.parametrize("case", ["no segmentation", "rule off"])
def test_nothing_changes_without_a_segmentation_or_with_the_rule_off(monkeypatch, case):
    moving = torch.zeros(H, W, dtype=torch.bool)
    moving[0:3, 0:4] = True
    if case == "no segmentation":
        w = _tracked(None, geometric=moving, monkeypatch=monkeypatch)
    else:
        w = _tracked(_seg(), geometric=moving, on=False, monkeypatch=monkeypatch)
    assert torch.equal(w[:, ~moving], torch.ones_like(w[:, ~moving]))  # only the geometry's region is taken out
    assert bool((w[:, moving] < 1).all())
