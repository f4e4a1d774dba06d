"""Another camera for the built-in scenarios: ``hfov_deg`` (same scene and trajectory, another lens)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pydantic import ValidationError

from pvslam_plugins.datasets.synthetic import generator, scenarios
from pvslam_plugins.datasets.synthetic.config import SyntheticConfig
from pvslam_plugins.datasets.synthetic.reader import SyntheticSequence
from pvslam_plugins.datasets.synthetic.render import Camera, render


@pytest.mark.parametrize("hfov", [45.0, 90.0, 120.0])
def test_the_focal_length_gives_the_field_of_view(hfov):
    cam = Camera.default(320, 240, hfov)
    assert math.degrees(2 * math.atan(0.5 * cam.width / cam.fx)) == pytest.approx(hfov, abs=1e-9)
    assert cam.fx == cam.fy and (cam.cx, cam.cy) == (159.5, 119.5)


def test_same_scene_and_trajectory_through_another_lens():
    # odd sizes: pixel (24, 32) is the principal point, on the optical axis whatever the focal length
    a = scenarios.build("handheld_fast", num_frames=3, width=65, height=49, seed=5)
    b = scenarios.build("handheld_fast", num_frames=3, width=65, height=49, seed=5, hfov_deg=100.0)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert a.camera.fx == pytest.approx(0.85 * 65) and b.camera.fx == pytest.approx(32.5 / math.tan(math.radians(50)))
    ra, rb = (render(s.scene, 1, s.poses[1], s.camera) for s in (a, b))
    assert rb.depth[24, 32] == pytest.approx(float(ra.depth[24, 32]), rel=1e-6)
    # the wider lens sees more of the scene: its image is not the default one's
    assert not np.array_equal(ra.rgb, rb.rgb)
    assert b.params["hfov_deg"] == 100.0 and "hfov_deg" not in a.params


def test_files_cache_and_reader_carry_the_camera(tmp_path, monkeypatch):
    monkeypatch.setenv("PVSLAM_CACHE", str(tmp_path / "cache"))
    # the default camera's cache key is the one it always had (no hfov in the hashed parameters)
    assert "hfov_deg" not in generator._params("indoor_handheld", 3, 48, 32, 0, None)
    wide = generator.ensure_cached("indoor_handheld", num_frames=3, width=48, height=32, progress=False,
                                   hfov_deg=90.0)
    default = generator.ensure_cached("indoor_handheld", num_frames=3, width=48, height=32, progress=False)
    assert wide != default
    meta = json.loads((wide / "meta.json").read_text())
    assert meta["hfov_deg"] == 90.0 and meta["camera"]["fx"] == pytest.approx(24.0)
    assert SyntheticSequence(wide).intrinsics.fx == pytest.approx(24.0)
    assert SyntheticSequence(default).intrinsics.fx == pytest.approx(0.85 * 48)
    # a folder that holds the sequence through another lens is not taken for this one (nothing is overwritten)
    out = generator.generate("indoor_handheld", tmp_path / "seq", num_frames=3, width=48, height=32, progress=False,
                             hfov_deg=70.0)
    assert generator.generate("indoor_handheld", out, num_frames=3, width=48, height=32, hfov_deg=70.0) == out
    with pytest.raises(FileExistsError):
        generator.generate("indoor_handheld", out, num_frames=3, width=48, height=32)
    # the reader plugin's option reaches the generator
    from pvslam_plugins.datasets.synthetic.reader import SyntheticReader

    r = SyntheticReader(SyntheticConfig(scenario="indoor_handheld", num_frames=3, width=48, height=32, progress=False,
                                        hfov_deg=90.0))
    assert r.info().intrinsics.fx == pytest.approx(24.0)


def test_a_field_of_view_no_pinhole_has_is_refused():
    with pytest.raises(ValueError, match="hfov_deg must be within 20-150 degrees"):
        scenarios.build("driving_loop", num_frames=2, width=64, height=48, hfov_deg=175.0)
    with pytest.raises(ValidationError, match="hfov_deg"):
        SyntheticConfig(hfov_deg=10.0)
