"""The motion filter decides on an angle of view, not on a pixel count: the same motion seen at twice the size
(twice the pixels of flow, twice the focal length) gives the same keyframe decision."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from dataclasses import replace

from pvslam_core.adapt import REF_BA_FOCAL, ba_px_scale
from pvslam_core.types import Intrinsics
from pvslam_plugins.frontends.flow import pair_flow
from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
from pvslam_plugins.frontends.flow.frontend import FlowFrontend

import _flow_scenes as S


def test_the_reference_camera_is_the_default_synthetic_one():
    """At the 320x240 default camera (fx = 0.85 W = 272) and 1/8 the factor is exactly 1: nothing changes there."""
    k = Intrinsics(272.0, 272.0, 159.5, 119.5, 320, 240)
    assert ba_px_scale(k, 8) == 1.0 and 272.0 / 8 == REF_BA_FOCAL
    assert ba_px_scale(k.scaled(2.0), 8) == pytest.approx(2.0)  # twice the size: twice the BA px per radian
    assert ba_px_scale(k, 4) == pytest.approx(2.0)  # a finer BA grid: the same


def _decisions(scale: int, shifts: list[float]) -> list[tuple[bool, float]]:
    """(is_keyframe, mean flow in BA px) of frames shifted by ``shifts`` px (at 320x240) from a keyframe, seen at
    ``scale`` times the size."""
    big = S.texture("astronaut")
    intr = replace(S.INTR.scaled(scale), width=S.W * scale, height=S.H * scale)

    def frame(img: np.ndarray, index: int):
        f = S.frame(cv2.resize(img, (S.W * scale, S.H * scale), interpolation=cv2.INTER_LINEAR), index)
        f.intrinsics = intr
        return f

    fe = FlowFrontend(FlowFrontendConfig())
    fe.add_keyframe(0, frame(S.base(big), 0), None)
    out = []
    for i, dx in enumerate(shifts, start=1):
        r = fe.track(frame(S.shifted(big, dx), i), None)
        assert not r.failed
        out.append((r.is_keyframe, r.mean_flow))
    return out


def test_the_keyframe_decision_does_not_depend_on_the_image_size(monkeypatch):
    monkeypatch.setattr(pair_flow, "TEXTURE_TAU", 0.0)
    shifts = [12.0, 24.0]  # 1.5 and 3 BA px at 320x240: under and over the threshold (2 reference BA px)
    small, large = _decisions(1, shifts), _decisions(2, shifts)
    assert [kf for kf, _ in small] == [False, True]
    assert [kf for kf, _ in large] == [False, True]  # 3 and 6 BA px at 640x480: the same angles
    for (_, a), (_, b) in zip(small, large):
        assert b == pytest.approx(2 * a, rel=0.1)  # the flow in BA px doubles with the size
