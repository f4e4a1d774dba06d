"""The core's seams for plugins that keep state: stable keyframe ids, the edge lifecycle, one loop policy that lets a
retrieval-only detector close loops, and segmenter categories in the outputs.  The plugins used here
(:mod:`fakes_seams`) are written against the public interfaces only."""
import json
from pathlib import Path

import numpy as np
import pytest

import fakes
import fakes_seams
from pvslam_core.adapt import REF_BA_FOCAL
from pvslam_core.api import run_config
from pvslam_core.outputs.ply import read_ply
from pvslam_core.registry import build_registry
from pvslam_core.slam import bootstrap


@pytest.fixture
def seams_registry():
    return build_registry(extra_modules=(fakes, fakes_seams))


def test_per_edge_state_follows_retirement_and_removal(seams_registry, fake_config_file):
    """A frontend with per-edge hidden state hears of every retired edge and removed keyframe: it never holds state
    the graph does not have, and its state stays bounded by the active window."""
    fakes_seams.StatefulFrontend.instances.clear()
    res = run_config(fake_config_file, registry=seams_registry, overrides=[
        'frontend.plugin="stateful"', "dataset.frames=60", "frontend.keyframe_every=1",
        # 0.2 BA px of the fake camera (f = 10 BA px at 1/4), in the config's reference BA px
        f"graph.keyframes.redundant_thresh={0.2 * REF_BA_FOCAL / (fakes.F / 4)}", "graph.edges.active_window=4",
        "graph.init.warmup=3"])
    fe = fakes_seams.StatefulFrontend.instances[-1]
    assert fe.errors == []
    tracking = res.metrics["tracking"]
    assert fe.removed, "the run should remove redundant keyframes"
    assert len(fe.retired) >= 40 and tracking["retired_edges"] > 0
    # bounded by the window, not the run: edges touching the last 4 keyframes, each with 3 neighbour and at most
    # 2 proximity edges to older keyframes, both directions (60 keyframes would hold ~300 edges)
    assert fe.max_state <= 4 * (3 + 2) * 2, fe.max_state
    assert len(fe.state) <= tracking["active_edges"]
    assert res.poses.shape == (60, 7) and np.isfinite(res.poses.numpy()).all()


@pytest.mark.parametrize("accept", [True, False])
def test_retrieval_only_detector_closes_loops(seams_registry, fake_config_file, accept):
    fakes.RecordingOptimizer.loop_calls = 0
    res = run_config(fake_config_file, registry=seams_registry, overrides=[
        'loop.plugin="retrieval_only"', "dataset.frames=30", f"loop_closure.accept_unverified={str(accept).lower()}"])
    if not accept:
        assert res.loops == [] and fakes.RecordingOptimizer.loop_calls == 0
        return
    assert res.loops and all(c.verified is None and c.kf_j == 1 for c in res.loops)
    assert fakes.RecordingOptimizer.loop_calls >= 1
    saved = json.loads((Path(res.run_dir) / "loops.json").read_text())["loops"]
    assert [(d["frame_i"], d["frame_j"]) for d in saved] == [(c.frame_i, c.frame_j) for c in res.loops]
    assert saved[0]["frame_j"] == 2  # keyframe id 1 is input frame 2 (every 2nd frame is a keyframe)


def test_segmenter_categories_reach_the_outputs(seams_registry, fake_config_file):
    """The dataset declares no categories; the segmenter's own appear in segments.json and the panoptic cloud."""
    res = run_config(fake_config_file, registry=seams_registry,
                     overrides=['segmenter.plugin="own_categories"', "dataset.frames=16"])
    d = Path(res.run_dir)
    seg = json.loads((d / "panoptic" / "segments.json").read_text())
    cats = {c["id"]: c for c in seg["categories"]}
    assert cats[9]["name"] == "robot" and cats[9]["isthing"] in (1, True)
    assert cats[7]["name"] == "lamp post"
    pts, cols, extra = read_ply(d / "cloud_panoptic.ply")
    assert len(pts) > 0 and set(np.unique(extra["category_id"]).tolist()) == {7, 9}
    robot = extra["category_id"] == 9
    # the segmenter's colours (thing instances are shaded): robots blue, lamp posts yellow
    r, g, b = cols[robot].astype(float).mean(0)
    assert b > r + 50 and b > g
    r, g, b = cols[~robot].astype(float).mean(0)
    assert r > b + 50 and g > b + 50


def test_edges_retire_before_initialisation(seams_registry, fake_config_file, monkeypatch):
    """A fragment that never initialises (warm-up longer than the run) keeps only the window's edges active and the
    frontend hears of the others, as after initialisation (it used to keep every neighbour edge of the run)."""
    fakes_seams.StatefulFrontend.instances.clear()
    monkeypatch.setattr(bootstrap, "WARMUP_SECONDS", 0)
    try:
        res = run_config(fake_config_file, registry=seams_registry, overrides=[
            'frontend.plugin="stateful"', "dataset.frames=40", "frontend.keyframe_every=1",
            "graph.edges.active_window=4", "graph.init.warmup=1000"])
        tracking = res.metrics["tracking"]
    except Exception as exc:  # a run without any pose estimate may stop with an error; the graph is what counts
        pytest.fail(f"run failed: {exc}")
    fe = fakes_seams.StatefulFrontend.instances[-1]
    assert not tracking["initialized"]
    assert 0 < tracking["active_edges"] <= 4 * 3 * 2, tracking
    assert len(fe.retired) >= 40 and fe.errors == []
