"""Run directories, ablations, the example third-party plugin and failure handling, on test-only plugins."""
import json

import numpy as np
import pytest

import fakes
from pvslam_core.api import run_ablation, run_config
from pvslam_core.config import load_config
from pvslam_core.outputs.trajectory_io import read_tum
from pvslam_core.slam import bootstrap, loops


def test_run_directory_contents(fake_registry, fake_config_file):
    res = run_config(fake_config_file, overrides=["run.name=framework"], registry=fake_registry)
    d = __import__("pathlib").Path(res.run_dir)
    assert d.name.startswith("framework-") and d.parent == fake_config_file.parent / "runs"
    for name in ("config.json", "overrides.json", "versions.json", "log.txt", "trajectory.txt", "keyframes.txt",
                 "groundtruth.txt", "metrics.json"):
        assert (d / name).is_file(), name
    # the resolved config reloads to the identical model
    again = load_config(d / "config.json", registry=fake_registry)
    assert again.pipeline == load_config(fake_config_file, overrides=["run.name=framework"],
                                         registry=fake_registry).pipeline
    ov = json.loads((d / "overrides.json").read_text())
    assert ov["overrides"] == {"run.name": "framework"}
    ver = json.loads((d / "versions.json").read_text())
    assert ver["plugins"]["frontend"]["plugin"] == "exact" and "revision" in ver["git"]
    assert ver["libraries"]["torch"]
    ts, poses = read_tum(d / "trajectory.txt")
    assert len(ts) == 12 and np.isfinite(poses).all()
    assert res.poses.shape == (12, 7)
    assert json.loads((d / "metrics.json").read_text())["timing"]["frames"] == 12


def test_ablation_runs_each_variant_and_prints_a_table(tmp_path, fake_registry):
    from pvslam_core.report import comparison_table

    p = tmp_path / "abl.toml"
    p.write_text(fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix())
                 + '\n[[variant]]\nname = "every2"\n\n[[variant]]\nname = "every3"\n"frontend.keyframe_every" = 3\n')
    results = run_ablation(p, registry=fake_registry)
    assert [n for n, _ in results] == ["every2", "every3"]
    dirs = [__import__("pathlib").Path(r.run_dir) for _, r in results]
    assert dirs[0] != dirs[1] and dirs[0].parent == dirs[1].parent
    assert dirs[0].name == "every2" and dirs[1].name == "every3"
    cfg3 = json.loads((dirs[1] / "config.json").read_text())
    assert cfg3["frontend"]["keyframe_every"] == 3
    assert json.loads((dirs[1] / "overrides.json").read_text())["overrides"] == {"frontend.keyframe_every": 3}
    table = comparison_table(results)
    assert "every2" in table and "every3" in table and "ATE" in table
    kf = [r.metrics["timing"]["keyframes"] for _, r in results]
    assert kf[0] > kf[1]  # the variant really changed the run
    assert (dirs[0].parent / "comparison.json").is_file()


def test_example_third_party_plugin_selected_by_config(tmp_path, fake_registry):
    from pvslam_npz import write_npz

    seq = write_npz(tmp_path / "seq.npz", fakes.FakeDataset(fakes.FakeDatasetConfig(frames=10)))
    cfg = tmp_path / "npz.toml"
    cfg.write_text(fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix())
                   .replace('plugin = "fake"\nframes = 12', f'plugin = "npz"\npath = "{seq.as_posix()}"'))
    res = run_config(cfg, registry=fake_registry)
    ver = json.loads((__import__("pathlib").Path(res.run_dir) / "versions.json").read_text())
    assert ver["plugins"]["dataset"] == {"plugin": "npz", "entry_point": "npz", "distribution": "pvslam-npz",
                                         "version": "0.1.0"}
    assert res.poses.shape[0] == 10


class _Broken(fakes.FakeDataset):
    def __iter__(self):
        for f in super().__iter__():
            if f.index == 8:
                raise ValueError("frame 8: corrupt image (test)")
            yield f


def test_failure_midway_keeps_what_was_written(tmp_path, fake_registry, monkeypatch):
    spec = fake_registry.get("dataset", "fake")
    monkeypatch.setattr(spec, "factory", lambda c, ctx: _Broken(c))
    cfg = tmp_path / "p.toml"
    cfg.write_text(fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix()))
    with pytest.raises(ValueError, match="corrupt image"):
        run_config(cfg, registry=fake_registry)
    (run_dir,) = list((tmp_path / "runs").iterdir())
    ts, poses = read_tum(run_dir / "trajectory.txt")
    assert len(ts) == 8 and np.isfinite(poses).all()
    assert json.loads((run_dir / "metrics.json").read_text())["partial"] is True
    assert "corrupt image" in (run_dir / "log.txt").read_text()


@pytest.mark.parametrize("tries, initialised", [(1, False), (3, True)])
def test_initialisation_falls_back_to_a_nearer_pair(fake_registry, fake_config_file, tries, initialised,
                                                   monkeypatch):
    """Fast motion: the flow from the first keyframe to the newest fails; a nearer partner still initialises (with
    the chained links of the far pair off: bootstrap.CHAIN_FALLBACK, the next test)."""
    monkeypatch.setattr(bootstrap, "INIT_TRIES", tries)
    monkeypatch.setattr(bootstrap, "CHAIN_FALLBACK", False)
    res = run_config(fake_config_file, registry=fake_registry,
                     overrides=["frontend.max_pair_gap=1", "graph.init.warmup=3",
                                "graph.init.min_parallax_deg=0.3"])
    log = (__import__("pathlib").Path(res.run_dir) / "log.txt").read_text()
    # the pairs all end at the newest keyframe (pvslam_core/slam/bootstrap.py): (0, 2) fails, (1, 2) initialises
    assert ("map initialised with keyframes 0..2 (pair 1-2" in log) == initialised, log
    assert ("never initialised" in log) != initialised
    if initialised:  # keyframe 0 (before the pair) was placed against keyframe 1: the camera's constant velocity
        x = res.keyframe_poses[:3, 0].numpy()
        assert x[2] != x[1] and abs((x[2] - x[1]) - (x[1] - x[0])) < 1e-3 * abs(x[2] - x[1])


def test_a_far_pair_whose_flow_failed_initialises_on_its_links(fake_registry, fake_config_file, monkeypatch):
    """The same fast motion with bootstrap.CHAIN_FALLBACK (on): the far pair (0, 2) takes its correspondences from
    the chained links 0 -> 1 -> 2, so the first try initialises."""
    monkeypatch.setattr(bootstrap, "INIT_TRIES", 1)
    res = run_config(fake_config_file, registry=fake_registry,
                     overrides=["frontend.max_pair_gap=1", "graph.init.warmup=3",
                                "graph.init.min_parallax_deg=0.3"])
    log = (__import__("pathlib").Path(res.run_dir) / "log.txt").read_text()
    assert "map initialised with keyframes 0..2 (pair 0-2" in log and "never initialised" not in log, log


@pytest.mark.parametrize("gap, expected", [(0, 8), (100, 1), (3, 3)])
def test_loop_ba_not_rerun_along_one_revisit(fake_registry, fake_config_file, gap, expected, monkeypatch):
    """Every keyframe from the 4th reports a loop with keyframe 1; from keyframe 5 to 12 each adds new loop edges
    (keyframe 4's are all there already). A loop BA runs only when the last one is loops.LOOP_BA_MIN_GAP
    keyframes old: gap 3 -> keyframes 5, 8 and 11.  (Suppression near accepted loops is off: it would keep all
    but the first of these closures.)"""
    fakes.RecordingOptimizer.loop_calls = 0
    monkeypatch.setattr(loops, "LOOP_BA_MIN_GAP", gap)
    monkeypatch.setattr(loops, "NMS_KEYFRAMES", 0)
    res = run_config(fake_config_file, registry=fake_registry,
                     overrides=['loop.plugin="every_kf"', "dataset.frames=26", "graph.init.warmup=3"])
    assert len(res.loops) == 8  # every accepted loop is recorded (loops.json, loop metrics)
    assert fakes.RecordingOptimizer.loop_calls == expected
    assert sum(c.loop_ba for c in res.loops) == expected


def test_the_map_stage_accounts_a_new_keyframes_setup(fake_registry, fake_config_file):
    """``timing.map_cpu_seconds`` has the setup of each new keyframe as a part of its own (``keyframe``), within the
    map stage's CPU like the other parts."""
    res = run_config(fake_config_file, overrides=["run.name=parts"], registry=fake_registry)
    t = res.metrics["timing"]
    parts = t["map_cpu_seconds"]
    assert t["keyframes"] > 1 and parts["keyframe"] > 0
    assert sum(parts.values()) <= t["stage_cpu_seconds"]["map"] + 1e-3


def test_the_timing_splits_the_steps_into_keyframe_steps_and_others(fake_registry, fake_config_file):
    """``timing.steps``: every frame's step counted once, as a keyframe step when the frame became a keyframe; their
    mean wall and pipeline-thread CPU add up to the stages' totals (the wait for the next frame is in neither)."""
    res = run_config(fake_config_file, overrides=["run.name=steps"], registry=fake_registry)
    t = res.metrics["timing"]
    kf, other = t["steps"]["keyframe"], t["steps"]["other"]
    assert kf["count"] + other["count"] == t["frames"] and kf["count"] >= t["keyframes"] > 1 and other["count"] > 0
    stages = ("segment", "map", "vps", "outputs")
    for key, total in (("wall_ms", sum(t["stage_seconds"][s] for s in stages)),
                       ("cpu_ms", sum(t["stage_cpu_seconds"][s] for s in stages))):
        assert (kf[key] * kf["count"] + other[key] * other["count"]) / 1000 == pytest.approx(total, abs=2e-3)


@pytest.mark.parametrize("source", ["built-in", "live", "third-party"])
def test_the_frontend_gets_the_next_frame_after_tracking_one_when_the_source_is_read_ahead(
        tmp_path, fake_registry, fake_config_file, monkeypatch, source):
    """A built-in reader's source of known length is read one frame ahead: frame ``i + 1`` goes to
    ``Frontend.prefetch`` after frame ``i`` was tracked (and added when it became a keyframe), before the next track.
    A live source (length unknown) is not, as its next frame may not exist yet; nor is another reader's (it may
    reuse or change a frame after yielding it, so it is not read ahead at all)."""
    from pvslam_core.types import SequenceInfo
    from pvslam_plugins.datasets.synthetic.reader import SyntheticReader
    from pvslam_plugins.frontends.flow.frontend import FlowFrontend

    frontend = fakes.ExactFrontend if source == "third-party" else FlowFrontend
    events = []
    track, add = frontend.track, frontend.add_keyframe
    monkeypatch.setattr(frontend, "track",
                        lambda self, frame, seg: events.append(("track", frame.index)) or track(self, frame, seg))
    monkeypatch.setattr(frontend, "add_keyframe", lambda self, kf_id, frame, seg: events.append(
        ("add", frame.index)) or add(self, kf_id, frame, seg))
    monkeypatch.setattr(frontend, "prefetch", lambda self, frame: events.append(("prefetch", frame.index)))
    if source == "third-party":
        res = run_config(fake_config_file, overrides=["run.name=ahead"], registry=fake_registry)
    else:
        if source == "live":
            info = SyntheticReader.info
            monkeypatch.setattr(SyntheticReader, "info", lambda self: SequenceInfo(
                **{**info(self).__dict__, "num_frames": None}))
        res = run_config(None, overrides=[
            'dataset.scenario="driving_loop"', "dataset.num_frames=12", f'run.output_dir="{tmp_path.as_posix()}"',
            "run.progress=false", "evaluation.enabled=false", "outputs.ply=false", "outputs.plots=false",
            "outputs.panoptic_png=false"])
    n = res.metrics["timing"]["frames"]
    assert n == 12 and ("track", 11) in events
    fetched = [i for kind, i in events if kind == "prefetch"]
    if source != "built-in":
        assert fetched == []
        return
    assert fetched == list(range(1, n))
    for i in fetched:  # after frame i - 1's track (and add), before frame i's track
        k = events.index(("prefetch", i))
        assert events[k - 1] in (("track", i - 1), ("add", i - 1)) and events[k + 1] == ("track", i)
