"""``panoptic_fpn`` inside the pipeline: COCO-style outputs with the segmenter's own categories, keyframes-only
segmentation when no VPS head reads every frame, and frames where nothing is found behaving as ``segmenter =
"none"``.  Short held-out clips of the synthetic generator (seed 100: never a training seed)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from pvslam_core.api import run_config
from pvslam_core.config import load_config
from pvslam_core.evaluation.coco_panoptic import coco_panoptic_problems
from pvslam_core.outputs.trajectory_io import read_tum
from pvslam_core.pipeline import Pipeline
from pvslam_plugins.segmenters.panoptic_fpn.checkpoint import save_checkpoint
from pvslam_plugins.segmenters.panoptic_fpn.config import reduced
from pvslam_plugins.segmenters.panoptic_fpn.data import synthetic_category_set
from pvslam_plugins.segmenters.panoptic_fpn.model import PanopticFPN

pytestmark = pytest.mark.slow
FRAMES = 24


@pytest.fixture(scope="module")
def clip():
    from pvslam_plugins.datasets.synthetic.generator import generate

    return generate("moving_vehicles", None, num_frames=FRAMES, seed=100, progress=False)


def overrides(tmp_path: Path, seq: Path, *extra: str) -> list[str]:
    return [f'run.output_dir="{(tmp_path / "runs").as_posix()}"', "run.progress=false",
            f'dataset.path="{seq.as_posix()}"', 'loop.plugin="none"', "outputs.ply=false", *extra]


def test_run_writes_coco_segments_with_the_segmenters_categories(tmp_path, clip):
    res = run_config(None, overrides=overrides(tmp_path, clip, 'segmenter.plugin="panoptic_fpn"'))
    d = Path(res.run_dir)
    meta = json.loads((d / "panoptic" / "segments.json").read_text())
    cats = synthetic_category_set()
    assert [(c["id"], c["name"], c["isthing"]) for c in meta["categories"]] == \
        [(c.id, c.name, int(c.isthing)) for c in cats.categories]
    assert len(meta["annotations"]) == FRAMES
    found = {s["category_id"] for a in meta["annotations"] for s in a["segments_info"]}
    assert {1, 3, 6, 11} <= found  # road, building, sky and cars are found on this street
    assert coco_panoptic_problems(d / "panoptic") == []
    m = json.loads((d / "metrics.json").read_text())
    assert m["panoptic"]["pq"] > 0.3  # against the clip's ground truth, through the VPS head
    ts, poses = read_tum(d / "trajectory.txt")
    assert len(ts) == FRAMES and np.isfinite(poses).all()


def test_keyframes_only_unless_vps_reads_every_frame(tmp_path, clip):
    counts = {}
    for vps in ("none", "warp_iou", "fusion"):
        cfg = load_config(None, overrides=overrides(tmp_path, clip, 'segmenter.plugin="panoptic_fpn"',
                                                    f'vps.plugin="{vps}"', f'run.name="{vps}"'))
        pipe = Pipeline(cfg)
        pipe.start()
        keyframes = 0
        for frame in pipe.dataset:
            keyframes += int(pipe.step(frame).is_keyframe)
        pipe.finish()
        counts[vps] = (pipe.segmenter.stats["frames_segmented"], keyframes)
    segmented, keyframes = counts["none"]
    assert 2 <= keyframes < FRAMES and segmented == keyframes
    assert counts["warp_iou"][0] == FRAMES
    # the fusion head reads only the features of a non-keyframe (it decodes its fused pyramid itself): the
    # segmenter's heads run for the keyframes and the first frame only
    assert counts["fusion"][0] <= counts["fusion"][1] + 1 < FRAMES


def test_frames_with_nothing_found_run_as_without_segmenter(tmp_path, clip):
    torch.manual_seed(0)
    weights = tmp_path / "random.pth"
    save_checkpoint(PanopticFPN(reduced(), synthetic_category_set()), weights)
    nothing = run_config(None, overrides=overrides(
        tmp_path, clip, 'segmenter.plugin="panoptic_fpn"', f'segmenter.weights="{weights.as_posix()}"',
        "segmenter.instances_confidence_thresh=1.0", "segmenter.stuff_area_limit=1000000000", 'run.name="nothing"'))
    none = run_config(None, overrides=overrides(tmp_path, clip, 'segmenter.plugin="none"', 'run.name="none"'))
    assert torch.allclose(nothing.poses, none.poses, atol=1e-9)
    d = Path(nothing.run_dir)
    meta = json.loads((d / "panoptic" / "segments.json").read_text())
    assert len(meta["annotations"]) == FRAMES and all(a["segments_info"] == [] for a in meta["annotations"])
    assert coco_panoptic_problems(d / "panoptic") == []
