"""The fusion head on the shipped reduced PanopticFPN: decode path, registration, trainer."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pvslam_core.interfaces import MotionCue
from pvslam_core.types import Frame, Intrinsics
from pvslam_plugins.segmenters.panoptic_fpn.segmenter import PanopticFPNSegmenter, PanopticFPNSegmenterConfig
from pvslam_plugins.vps.fusion.config import FusionConfig
from pvslam_plugins.vps.fusion.head import FusionHead
from pvslam_plugins.vps.fusion.layer import FeatureFusion

H, W = 96, 128


def _image(shift: int) -> torch.Tensor:
    """A road scene of sorts: grey ground, blue sky, a red box that moves ``shift`` px to the right."""
    img = np.zeros((H, W, 3), np.uint8)
    img[: H // 3] = (110, 160, 230)
    img[H // 3:] = (90, 90, 95)
    img[40:70, 30 + shift:70 + shift] = (200, 30, 30)
    return torch.from_numpy(img.transpose(2, 0, 1).copy())


def _frame(i: int, shift: int) -> Frame:
    return Frame(index=i, timestamp=0.1 * i, image=_image(shift), intrinsics=Intrinsics(100.0, 100.0, 64, 48, W, H))


@pytest.fixture(scope="module")
def segmenter():
    return PanopticFPNSegmenter(PanopticFPNSegmenterConfig(frames="all"))


def test_identity_fusion_decodes_like_the_segmenter(segmenter):
    head = FusionHead(FusionConfig(), model=segmenter.model, fusion=FeatureFusion(64))  # identity layer
    f0, f1 = _frame(0, 0), _frame(1, 4)
    s0, s1 = segmenter.segment(f0), segmenter.segment(f1)
    state = head.update(None, f0, s0, MotionCue())
    cue = MotionCue(flow=torch.full((2, H // 8, W // 8), 0.5))  # 0.5 cue px = 4 frame px
    fused = head.fuse(state, f1, s1, cue)
    assert fused is not None
    assert torch.equal(fused.ids, s1.ids)  # fused = current features exactly -> the same decode
    assert [(s.category_id, s.isthing) for s in fused.segments] == [(s.category_id, s.isthing) for s in s1.segments]
    out = head.update(state, f1, s1, cue)
    assert out.panoptic.features is s1.features  # the next frame warps the unfused features
    assert out.panoptic.ids.shape == (H, W)


def test_shipped_fusion_weights_run(segmenter):
    head = FusionHead(FusionConfig(), model=segmenter.model)
    state = None
    for i in range(2):
        f = _frame(i, 3 * i)
        cue = MotionCue(flow=torch.full((2, H // 8, W // 8), 3 / 8)) if i else MotionCue()
        state = head.update(state, f, segmenter.segment(f), cue)
        ids = state.panoptic.ids
        assert set(torch.unique(ids).tolist()) - {0} <= {s.id for s in state.panoptic.segments}


def test_registered_with_a_trainer():
    import pvslam_plugins.vps.fusion as plugin
    from pvslam_core.registry import build_registry

    reg = build_registry()
    if ("vps", "fusion") not in reg.plugins:  # entry point not installed yet: register the module directly
        reg = build_registry(extra_modules=(plugin,))
    spec = reg.get("vps", "fusion")
    assert spec.extras.get("trainer") is not None
    head = spec.factory(FusionConfig(fuse=False), None)
    assert isinstance(head, FusionHead)
