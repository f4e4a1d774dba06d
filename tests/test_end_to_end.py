"""End-to-end runs of the default pipeline on short built-in synthetic sequences (real plugins, no fakes)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from pvslam_core.api import run_config
from pvslam_core.config_base import PluginConfig
from pvslam_core.interfaces import DatasetReader
from pvslam_core.outputs.trajectory_io import read_tum
from pvslam_core.registry import build_registry, hookimpl

pytestmark = pytest.mark.slow
FRAMES = 140


@pytest.fixture(scope="module")
def driving_seq():
    from pvslam_plugins.datasets.synthetic.generator import generate

    return generate("driving_loop", None, num_frames=FRAMES, progress=False)


def _run(tmp_path: Path, seq: Path, *extra: str, registry=None):
    overrides = [f'run.output_dir="{(tmp_path / "runs").as_posix()}"', "run.progress=false",
                 f'dataset.path="{seq.as_posix()}"', *extra]
    return run_config(None, overrides=overrides, registry=registry)


def test_default_pipeline_short_driving_sequence(tmp_path, driving_seq):
    res = _run(tmp_path, driving_seq)
    d = Path(res.run_dir)
    m = json.loads((d / "metrics.json").read_text())
    ate = m["ate"]
    # A loop-free stretch of the driving loop (about 93 m, one 90-degree turn): measured 0.18 % with the defaults
    # (labels + VPS on). The same bound as DRIVE_BOUND in test_regressions.py, whose tests of the test show that
    # BA off (11.2 %) or robust kernels off (3.1 %) break it.
    assert ate["rmse_percent_of_path"] < 1.5, ate
    assert m["timing"]["frames"] == FRAMES and m["timing"]["keyframes"] >= 10
    assert m["tracking"]["scale_gaps"] == []  # a drive measures depth all along (pvslam_core/slam/scale_gaps.py)
    assert m["panoptic"]["pq"] > 0.99  # oracle labels + tracking keep ids
    assert m["panoptic"]["vpq"] > 0.9
    ts, poses = read_tum(d / "trajectory.txt")
    assert len(ts) == FRAMES and np.isfinite(poses).all()
    for name in ("cloud_rgb.ply", "cloud_panoptic.ply", "keyframes.txt", "plots/trajectory_top.png",
                 "plots/ate_over_time.png", "panoptic/000000.png", "panoptic/segments.json", "loops.json"):
        assert (d / name).is_file(), name
    _pvslam_eval_matches_evo_cli(d, tmp_path, ate["rmse"])


def _pvslam_eval_matches_evo_cli(run_dir: Path, tmp_path: Path, rmse_run: float) -> None:
    """`pvslam eval RUN_DIR` recomputes the ATE, and it equals evo's own command line on the same files."""
    import contextlib
    import io
    import os
    import subprocess
    import sys
    import zipfile

    from pvslam_core.cli import main

    (run_dir / "metrics.json").unlink()
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["eval", str(run_dir)]) == 0
    rmse_eval = json.loads(buf.getvalue())["ate"]["rmse"]
    assert rmse_eval == pytest.approx(rmse_run, rel=1e-12)
    exe = Path(sys.executable).parent / "evo_ape"
    out = tmp_path / "evo.zip"
    subprocess.run([str(exe), "tum", str(run_dir / "groundtruth.txt"), str(run_dir / "trajectory.txt"), "-as",
                    "--save_results", str(out), "--no_warnings"], check=True, capture_output=True, timeout=120,
                   env=dict(os.environ, HOME=str(tmp_path), MPLBACKEND="Agg"))
    with zipfile.ZipFile(out) as z:
        rmse_evo = json.loads(z.read("stats.json"))["rmse"]
    assert rmse_eval == pytest.approx(rmse_evo, rel=1e-9)


class _PerturbedConfig(PluginConfig):
    path: str
    black: list[int] = []
    repeat: list[int] = []
    jump_at: int = -1
    jump_by: int = 0


class _Perturbed(DatasetReader):
    """The synthetic sequence with a black frame, repeated frames and a sudden jump (frames skipped)."""

    def __init__(self, cfg: _PerturbedConfig):
        from pvslam_plugins.datasets.synthetic.config import SyntheticConfig
        from pvslam_plugins.datasets.synthetic.reader import make_reader
        from pvslam_core.interfaces import BuildContext

        self.cfg = cfg
        self.inner = make_reader(SyntheticConfig(path=cfg.path), BuildContext(device=torch.device("cpu")))

    def info(self):
        from dataclasses import replace

        info = self.inner.info()
        return replace(info, num_frames=info.num_frames + len(self.cfg.repeat) - max(self.cfg.jump_by, 0),
                       loop_pairs=None)

    def __iter__(self):
        out = 0
        frames = list(self.inner)
        src = 0
        while src < len(frames) and out < self.info().num_frames:
            if src == self.cfg.jump_at:
                src += self.cfg.jump_by
            f = frames[src]
            f.index = out
            if out in self.cfg.black:
                f.image = torch.zeros_like(f.image)
            yield f
            out += 1
            if out - 1 in self.cfg.repeat:
                g = frames[src]
                g.index, g.timestamp = out, f.timestamp + 1e-3
                yield g
                out += 1
            src += 1


class _PerturbedPlugin:
    @staticmethod
    @hookimpl
    def register_datasets(register):
        register("perturbed", lambda c, ctx: _Perturbed(c), _PerturbedConfig, description="test-only")


JUMP_AT, JUMP_BY = 70, 25  # source frames skipped: a 16.7 m jump, nothing to track across it


def _jump_run(tmp_path: Path, seq: Path, *extra: str):
    """The perturbed sequence of the re-initialisation tests: (result, log text, est ts/poses, gt ts/poses)."""
    reg = build_registry(extra_modules=(_PerturbedPlugin,))
    res = run_config(None, registry=reg, overrides=[
        "dataset.plugin=perturbed", f'run.output_dir="{(tmp_path / "runs").as_posix()}"', "run.progress=false",
        f'dataset.path="{seq.as_posix()}"', "dataset.black=[30]", "dataset.repeat=[45]",
        f"dataset.jump_at={JUMP_AT}", f"dataset.jump_by={JUMP_BY}", "segmenter.plugin=none", "vps.plugin=none",
        "loop.plugin=none", "outputs.ply=false", "outputs.plots=false", *extra])
    d = Path(res.run_dir)
    ts, poses = read_tum(d / "trajectory.txt")
    gts, gt = read_tum(d / "groundtruth.txt")
    return res, (d / "log.txt").read_text(), ts, poses, gts, gt


def _segment_ate(ts, poses, gts, gt, a: int, b: int) -> float:
    """ATE (% of path) of frames [a, b) aligned on their own (Sim(3)): how good one fragment is by itself."""
    from pvslam_core.evaluation.trajectory import ate

    return ate(ts[a:b], poses[a:b], gts[a:b], gt[a:b])["rmse_percent_of_path"]


FRAGMENT_BOUND = 1.5  # % of path, each fragment on its own


def test_tracking_failures_reinitialise_a_new_fragment(tmp_path, driving_seq):
    """A black frame (skipped, no re-initialisation), a repeated frame, then a sudden 25-frame jump: tracking
    against the last keyframe fails for ``graph.reinit_after`` frames, the map re-initialises as a new fragment,
    and the trajectory still has one finite pose per input frame.

    Measured on dataset seeds 0 / 1 / 2 (the test runs seed 0): failures at frame 30 and 71-74, re-initialisation
    at frame 74; fragment ATE (each aligned on its own) 0.51 / 0.57 / 0.43 % before the jump, 0.49 / 0.57 / 0.70 %
    after; whole-trajectory ATE 6.98 / 7.82 / 7.55 %: the two fragments are not merged (no loop here; the jump is
    not observable and each fragment has its own monocular scale), which is why the whole-trajectory bound is loose.
    """
    import re

    res, log, ts, poses, gts, gt = _jump_run(tmp_path, driving_seq)
    n = FRAMES + 1 - JUMP_BY
    jump = JUMP_AT + 1  # output index of the first frame after the jump (one repeated frame before it)
    assert re.search(r"frame 30 \(.*\): tracking failed: no texture", log)  # the black frame is reported ...
    assert not re.search(r"re-initialising the map at frame 3[0-4]\b", log)  # ... and skipped, not re-initialised
    reinit = [int(x) for x in re.findall(r"re-initialising the map at frame (\d+)", log)]
    assert len(reinit) == 1 and jump <= reinit[0] <= jump + 6, reinit  # reinit_after = 4 failures after the jump
    t = res.metrics["timing"]
    assert t["reinitialisations"] == 1 and 5 <= t["tracking_failures"] <= 8, t
    assert "map initialised with keyframes" in log.split("re-initialising the map")[1]  # the new fragment started
    # every frame has a pose, the failed ones included
    assert len(ts) == len(gts) == n == res.poses.shape[0] and np.isfinite(poses).all()
    assert np.all(np.diff(ts) > 0)
    # Each fragment is a good trajectory on its own (Sim(3) aligned separately) ...
    for a, b in ((0, jump), (reinit[0], n)):
        assert _segment_ate(ts, poses, gts, gt, a, b) < FRAGMENT_BOUND, (a, b)
    # ... and the whole trajectory is still one usable estimate (loose: fragments are not merged, see above).
    whole = res.metrics["ate"]["rmse_percent_of_path"]
    assert whole < 15.0, whole


def test_reinit_test_catches_no_reinitialisation(tmp_path, driving_seq):
    """Test of the test above: with re-initialisation effectively off (``graph.reinit_after`` beyond the sequence),
    every frame after the jump fails against the last keyframe of the lost map and holds its pose, so the
    post-jump fragment bound fails.  Measured (seeds 0 / 1 / 2): 41 / 42 / 42 failures, no re-initialisation, ATE of
    frames 74-115 (aligned on their own) 24.6 / 25.8 / 25.6 %."""
    res, log, ts, poses, gts, gt = _jump_run(tmp_path, driving_seq, "graph.reinit_after=1000")
    n = FRAMES + 1 - JUMP_BY
    assert res.metrics["timing"]["reinitialisations"] == 0
    assert len(ts) == n and np.isfinite(poses).all()  # still a pose per frame
    after = _segment_ate(ts, poses, gts, gt, JUMP_AT + 4, n)
    assert not after < FRAGMENT_BOUND, after


MERGE_GAP_BOUND = 1.0  # metres: RMSE of the first fragment and the revisit frames aligned together


@pytest.mark.parametrize("loop", [True, False], ids=["default", "loop_off"])
def test_fragment_after_a_loss_is_merged_at_the_revisit(tmp_path, loop):
    """driving_block (a revisit after ~190 frames) with a 40-frame jump at frame 60: tracking is lost, the map
    re-initialises as a second fragment, and the loop detector's revisit of the start joins it to the first one,
    so the frames after the revisit sit in the first fragment's frame.  With loop closure off (the test of this
    test) the fragments stay apart and that check fails.

    Measured on dataset seeds 0 / 1 / 2 (the test runs seed 0): 4 failures from frame 60, re-initialisation at
    frame 63, fragments merged at the revisit (seed 0: the loop from frame 152 to frame 2).  Frames 0-59 and
    150-188 aligned together (one Sim(3)): RMSE 0.15 / 0.21 / 0.09 m merged, 11.0 / 6.4 / 6.3 m with loop closure
    off.  First fragment 0.27 / 0.47 / 0.24 %.  Whole trajectory 6.1 / 0.64 / 0.72 % merged, 8.7 / 5.9 / 6.1 %
    apart: on seed 0 the second fragment is itself poor (12 % on frames 63-150: its two-view initialisation right
    after the jump), so the whole-trajectory bound is loose.  Fragment merging and re-initialisation are being
    reworked: tighten it then.
    """
    import re

    from pvslam_core.evaluation.trajectory import ate
    from pvslam_plugins.datasets.synthetic.generator import generate

    block = generate("driving_block", None, progress=False)  # cached, shared with tests/test_regressions.py
    reg = build_registry(extra_modules=(_PerturbedPlugin,))
    res = run_config(None, registry=reg, overrides=[
        "dataset.plugin=perturbed", f'run.output_dir="{(tmp_path / "runs").as_posix()}"', "run.progress=false",
        f'dataset.path="{block.as_posix()}"', "dataset.jump_at=60", "dataset.jump_by=40", "segmenter.plugin=none",
        "vps.plugin=none", "outputs.ply=false", "outputs.plots=false", *([] if loop else ["loop.plugin=none"])])
    d = Path(res.run_dir)
    log = (d / "log.txt").read_text()
    t = res.metrics["timing"]
    assert t["reinitialisations"] == 1 and 4 <= t["tracking_failures"] <= 8, t
    reinit = [int(x) for x in re.findall(r"re-initialising the map at frame (\d+)", log)]
    assert len(reinit) == 1 and 60 <= reinit[0] <= 66, reinit
    ts, poses = read_tum(d / "trajectory.txt")
    gts, gt = read_tum(d / "groundtruth.txt")
    n = 229 - 40
    assert len(ts) == len(gts) == n == res.poses.shape[0] and np.isfinite(poses).all()
    first = _segment_ate(ts, poses, gts, gt, 0, 60)
    assert first < FRAGMENT_BOUND, first
    idx = np.r_[0:60, 150:n]  # before the loss, and after the revisit of the start
    joint = ate(ts[idx], poses[idx], gts[idx], gt[idx])["rmse"]
    tr = res.metrics["tracking"]
    assert tr["fragments"] == 2, tr
    if not loop:
        assert not re.search(r"fragments merged", log)
        assert tr["fragment_merges"] == 0 and tr["maps"] == 2, tr
        assert not joint < MERGE_GAP_BOUND, joint
        return
    assert re.search(r"fragments merged", log), "the second fragment was never joined to the first"
    assert not re.search(r"never joined", log)
    assert tr["fragment_merges"] == 1 and tr["maps"] == 1, tr  # one trajectory in one frame
    assert joint < MERGE_GAP_BOUND, joint
    assert res.metrics["ate"]["rmse_percent_of_path"] < 15.0, res.metrics["ate"]
