"""A head camera that stops and turns on the spot, wider than its field of view (the synthetic ``handheld_fast``,
seed 123, first 260 frames): the run reports the stretch where its scale was not observed
(``tracking.scale_gaps``, pvslam_core/slam/scale_gaps.py) at the turn, and warns."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pvslam_core.api import run_config

pytestmark = pytest.mark.slow
FRAMES = 260


@pytest.fixture(scope="module")
def spin_seq():
    from pvslam_plugins.datasets.synthetic.generator import generate

    return generate("handheld_fast", None, num_frames=FRAMES, seed=123, progress=False)


def _stand(gt: np.ndarray) -> tuple[int, int]:
    """The ground truth's stand: the longest run of frames moving < 2 mm a frame (it turns > 61 deg within it)."""
    still = np.linalg.norm(np.diff(gt[:, 1:4], axis=0), axis=1) < 0.002
    runs, a = [], None
    for f, s in enumerate(still):
        if s and a is None:
            a = f
        if not s and a is not None:
            runs.append((a, f))
            a = None
    a, b = max(runs, key=lambda r: r[1] - r[0])
    rot = Rotation.from_quat(gt[:, 4:8])
    assert np.degrees((rot[a].inv() * rot[b]).magnitude()) > 61.0, (a, b)
    return a, b


def test_the_turn_on_the_spot_is_reported(tmp_path, spin_seq):
    res = run_config(None, overrides=[
        f'run.output_dir="{(tmp_path / "runs").as_posix()}"', "run.progress=false",
        f'dataset.path="{Path(spin_seq).as_posix()}"', "segmenter.plugin=none", "vps.plugin=none",
        "outputs.ply=false", "outputs.plots=false", "outputs.panoptic_png=false"])
    d = Path(res.run_dir)
    a, b = _stand(np.loadtxt(d / "groundtruth.txt"))  # (140, 197): the turn is at frames 156-180
    m = json.loads((d / "metrics.json").read_text())
    gaps = m["tracking"]["scale_gaps"]
    wide = [g for g in gaps if g["beyond_fov"] and g["first_frame"] <= b and g["last_frame"] >= a]
    assert len(wide) == 1, gaps
    g = wide[0]
    # it starts in the stand and lasts until the walk has measured depth again (each keyframe judged by its share after
    # its own window BA; judged at the end of the run instead, it ended mid-turn at frame 174)
    assert a <= g["first_frame"] <= b <= g["last_frame"], (g, (a, b))
    assert g["turn_deg"] > 61.0 and g["unmeasured"] >= 2, g
    log = (d / "log.txt").read_text()
    assert f"frames {g['first_frame']}-{g['last_frame']}: the camera turned" in log
    # the evaluation aligns the parts before and after it on their own too (ate_segments)
    parts = m["ate_segments"]
    assert [p["start"] for p in parts] == [0.0, g["first_time"]] and sum(p["num_pairs"] for p in parts) == FRAMES
    assert all(p["rmse"] <= m["ate"]["rmse"] for p in parts), (parts, m["ate"])
