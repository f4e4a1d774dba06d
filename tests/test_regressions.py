"""Accuracy bounds that fail when a core piece of the default pipeline breaks, and tests of those tests.

Each bound is checked on the default configuration (it must hold) and on a deliberately broken configuration (it
must NOT hold), so a change that switches a piece off without anyone noticing fails the suite:

* dense BA off (``optimizer.iters = 0``, no final / loop BA) and robust kernels off (least squares in the BA and
  the motion-only BA) on a 140-frame loop-free stretch of the driving loop;
* loop closure off on ``driving_block`` (the driving loop around a small block: a revisit after ~190 frames);
* dynamic masking off on a street with moving vehicles (oracle labels, so only the masking differs; the flow
  frontend's texture term off, since it protects that street on its own);
* DIS's patch-mean normalisation off on the drive with auto-exposure changes;
* the movable things out of the tracking weights on a bus that fills the view (oracle labels).

Runs are bit-reproducible on one machine (one torch thread), so each figure in a test is one run (but one draw of a
chaotic figure: the exposure test takes a median over three brightness levels); the bounds sit
between the good and broken values measured over dataset seeds 0, 1, 2 (figures in the comments: ``run_config``
with each test's overrides on ``generate(scenario, num_frames=..., seed=s)``; the commit that measured them is in
``git log -- tests/test_regressions.py``).  The tests run seed 0.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pvslam_core.api import run_config

pytestmark = pytest.mark.slow

BA_OFF = ["optimizer.iters=0", "optimizer.final.iters=0", "optimizer.loop.iters=0"]
ROBUST_OFF = ['optimizer.robust="none"']  # and the motion-only BA's kernel: map_state.MOTION_ROBUST (robust_off)
LOOP_OFF = ["loop.plugin=none"]
MASK_OFF = ["frontend.dynamic.enabled=false"]
ROAD_OFF = ["frontend.road.enabled=false"]  # no road plane, so no road depth prior: the map's scale may drift
NO_SEG = ["segmenter.plugin=none", "vps.plugin=none"]  # nothing in these scenes needs labels: cheaper runs


def _seq(scenario: str, frames: int | None = None) -> Path:
    from pvslam_plugins.datasets.synthetic.generator import generate

    return generate(scenario, None, num_frames=frames, progress=False)  # cached, shared with other tests


def _overrides(out: Path, seq: Path, *extra: str) -> list[str]:
    plugin = [e for e in extra if e.startswith("dataset.plugin=")]  # before the plugin's own keys
    return [*plugin, f'run.output_dir="{out.as_posix()}"', "run.progress=false", f'dataset.path="{seq.as_posix()}"',
            "outputs.ply=false", "outputs.plots=false", *(e for e in extra if e not in plugin)]


def _run(out: Path, seq: Path, *extra: str, registry=None):
    res = run_config(None, overrides=_overrides(out, seq, *extra), registry=registry)
    assert not res.metrics.get("failed"), res.metrics
    return res


def _ate(res) -> float:
    a = res.metrics.get("ate", {}).get("rmse_percent_of_path")
    return float(a) if a is not None else math.nan


# ------------------------------------------------------------------------------------- BA and robust kernels --
DRIVE_FRAMES = 140  # the same cached sequence as tests/test_end_to_end.py
# ATE, % of the ~93 m path (dataset seeds 0 / 1 / 2):
#   default             0.18 / 0.21 / 0.51   (full default with labels + VPS, seed 0: 0.18)
#   BA off             11.2  / 10.8 / 12.2
#   robust kernels off  3.14 / 2.91 / 2.42
# The bound leaves about 3x above the worst default and 1.6x below the best robust-off run.
DRIVE_BOUND = 1.5


@pytest.fixture(scope="module")
def drive140():
    return _seq("driving_loop", DRIVE_FRAMES)


@pytest.fixture(scope="module")
def drive_good(tmp_path_factory, drive140):
    """The default run (labels and VPS off)."""
    return _run(tmp_path_factory.mktemp("drive_good"), drive140, *NO_SEG)


def test_default_drive_within_bound(drive_good):
    ate = _ate(drive_good)
    assert ate < DRIVE_BOUND, ate
    t = drive_good.metrics["timing"]
    assert t["tracking_failures"] == 0 and t["reinitialisations"] == 0
    assert drive_good.poses.shape[0] == DRIVE_FRAMES and np.isfinite(drive_good.poses.numpy()).all()


@pytest.mark.parametrize("broken", [BA_OFF, ROBUST_OFF], ids=["ba_off", "robust_off"])
def test_bound_catches_broken_drive(tmp_path, drive140, broken, monkeypatch):
    """Test of the test above: with the piece switched off, the same bound fails (the run itself still works)."""
    if broken is ROBUST_OFF:
        from pvslam_core.slam import map_state

        monkeypatch.setattr(map_state, "MOTION_ROBUST", "none")  # least squares in the motion-only BA too
    res = _run(tmp_path, drive140, *NO_SEG, *broken)
    assert res.poses.shape[0] == DRIVE_FRAMES and np.isfinite(res.poses.numpy()).all()
    ate = _ate(res)
    assert not ate < DRIVE_BOUND, ate


def _exposure_run(out: Path, drive: Path, brightness: float):
    """The drive through the ``images`` reader (no labels), every image scaled by ``brightness`` and by a camera's
    auto-exposure (the synthetic plugin's ``exposure.auto_exposure_gain``: a 1.5x ramp over frames 30-60, held, a
    0.7x step at frame 90 and back at 120)."""
    from pvslam_plugins.datasets.synthetic.exposure import exposure_copy

    seq = exposure_copy(drive, out / "seq", brightness)
    fps = json.loads((seq / "meta.json").read_text()).get("fps", 12.0)
    calib, gt = (seq / "calib.txt").as_posix(), (seq / "groundtruth.txt").as_posix()
    res = _run(out / "runs", seq / "rgb", 'dataset.plugin="images"', f'dataset.calib="{calib}"',
               f"dataset.fps={fps}", f'dataset.groundtruth="{gt}"', *NO_SEG)
    assert res.poses.shape[0] == DRIVE_FRAMES and np.isfinite(res.poses.numpy()).all()
    return res


# One run of this drive is one draw of a chaotic figure: the same frames 10 % brighter or darker move the ATE by up
# to 4x (texture term off, no exposure changes, dataset seeds 0 / 1 / 2 at brightness 0.9 / 1.0 / 1.1: 0.14-0.68 %),
# so the test bounds the median over three brightness levels.  Measured (seed 0; images reader, no labels; texture
# term on): with the exposure changes 0.37 / 0.88 / 0.19 % (median 0.37), without 0.29 / 0.22 / 0.30 % (median 0.29);
# the bound is 2 x 0.29 + 0.1 = 0.68 %.  With DIS's patch-mean normalisation off (what lets a flow survive a gain
# change) tracking fails at the 0.7x step (97-99 % of the pixels fail the forward-backward check) and the map
# re-initialises: 1.67 / 1.80 / 1.78 %; without exposure changes 0.24 / 0.27 / 0.23 %.  The photometric confidence's
# gain fit (flow_ops.fit_exposure) makes no measurable difference here; it has its own unit test.
BRIGHTNESS = (0.9, 1.0, 1.1)
EXPOSURE_BOUND = 0.68  # on the median over BRIGHTNESS


def test_drive_with_exposure_changes_within_bound(tmp_path, drive140):
    """Real cameras change exposure: DIS normalises each patch's mean and the photometric confidence removes a
    fitted global gain and offset, so gain ramps and steps must not break tracking or the scale."""
    runs = [_exposure_run(tmp_path / f"expo{b}", drive140, b) for b in BRIGHTNESS]
    for res in runs:
        t = res.metrics["timing"]
        assert t["tracking_failures"] == 0 and t["reinitialisations"] == 0
    expo = [_ate(res) for res in runs]
    assert max(expo) < DRIVE_BOUND and np.median(expo) < EXPOSURE_BOUND, expo


def test_exposure_bound_catches_a_flow_without_mean_normalisation(tmp_path, drive140, monkeypatch):
    """Test of the test above: DIS without its patch-mean normalisation loses track at the exposure step and the scale
    across the ramp, and fails that test (one draw is enough: 1.67-1.80 % at each brightness)."""
    from pvslam_plugins.frontends.flow import flow_ops

    create = flow_ops.create_dis

    def no_mean_normalisation(*args, **kwargs):
        dis = create(*args, **kwargs)
        dis.setUseMeanNormalization(False)
        return dis

    monkeypatch.setattr(flow_ops, "create_dis", no_mean_normalisation)
    res = _exposure_run(tmp_path, drive140, 1.0)
    assert res.metrics["timing"]["tracking_failures"] > 0 and not _ate(res) < EXPOSURE_BOUND, _ate(res)


# ------------------------------------------------------------------------------------------ loop closure --
# driving_block (229 frames, 152 m): ground-truth revisits (within 3 m) are frames 204-228 against frames 0-24.
# "Loop gap": for every ground-truth loop pair (i, j), after the Sim(3) alignment of the whole trajectory,
# | (p_i - p_j) - (g_i - g_j) |: how far apart the estimate puts two places that are the same place.  It is what
# loop closure fixes directly; the whole-trajectory ATE moves less (a loop spreads the drift it removes).
# Dataset seeds 0 / 1 / 2:
#   loop closure on:  ATE 0.118 / 0.139 / 0.145 %, mean loop gap 0.17 / 0.16 / 0.15 m, 2 verified loops each
#                     (one true; the other, frame ~190 -> 0-2, sees the start from ~10 m before it, outside the
#                     3 m ground-truth radius, and is scored a false positive)
#   loop closure off: ATE 0.316 / 0.257 / 0.586 %, mean loop gap 1.72 / 1.31 / 3.26 m
LOOP_GAP_BOUND = 0.5  # metres
LOOP_ATE_RATIO = 0.75  # loop closure on must be below this fraction of the ATE with it off (measured 0.25-0.54)


@pytest.fixture(scope="module")
def block():
    return _seq("driving_block")


def _shared_run(tmp_path_factory, key: str, seq: Path, *extra: str):
    """``_run`` once per test session even under pytest-xdist: these runs feed tests that xdist may send to
    different workers, so the first worker to need one computes it (under a file lock, in the base temp folder
    all workers share) and the others load its pickled result (bit-identical tensors, the same run folder)."""
    import os
    import pickle

    from filelock import FileLock  # a dependency of torch

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's base folder, above the per-worker ones
    out = root / f"shared_run_{key}"
    with FileLock(str(out) + ".lock"):
        pkl = out / "result.pkl"
        if pkl.is_file():
            return pickle.loads(pkl.read_bytes())
        res = _run(out, seq, *extra)
        pkl.write_bytes(pickle.dumps(res))
        return res


@pytest.fixture(scope="module")
def block_on(tmp_path_factory, block):
    return _shared_run(tmp_path_factory, "block_on", block, *NO_SEG)


@pytest.fixture(scope="module")
def block_off(tmp_path_factory, block):
    return _shared_run(tmp_path_factory, "block_off", block, *NO_SEG, *LOOP_OFF)


def _loop_gap(res) -> float:
    """Mean loop gap (metres, see above) over the ground-truth loop pairs, written by the run itself."""
    from pvslam_core.evaluation.trajectory import aligned_positions
    from pvslam_core.outputs.trajectory_io import read_tum

    d = Path(res.run_dir)
    ts, est = read_tum(d / "trajectory.txt")
    gts, gt = read_tum(d / "groundtruth.txt")
    pairs = np.asarray(json.loads((d / "groundtruth_loops.json").read_text())["pairs"])  # [P, 2] frame indices
    assert len(pairs) > 0 and len(ts) == len(gts)
    r = aligned_positions(ts, est, gts, gt, align="sim3")
    e, g = np.asarray(r["est_xyz"]), np.asarray(r["gt_xyz"])  # [N, 3] each, frame order
    assert len(e) == len(g) == len(ts), "every frame must be associated for frame-index lookups"
    i, j = pairs[:, 0], pairs[:, 1]
    return float(np.linalg.norm((e[i] - e[j]) - (g[i] - g[j]), axis=1).mean())


def _closes_loop(res) -> None:
    """The assertions of the loop test, shared with its test of the test."""
    path = Path(res.run_dir) / "loops.json"
    loops = json.loads(path.read_text())["loops"] if path.is_file() else []
    verified = [lp for lp in loops if lp["verified"] and lp.get("loop_ba", True)]
    assert verified, f"no geometrically verified loop that reached the BA: {loops}"
    cfg = json.loads((Path(res.run_dir) / "config.json").read_text())["loop"]
    assert all(lp["inliers"] >= cfg["min_inliers"] for lp in verified), (verified, cfg)  # RANSAC essential-matrix
    assert res.metrics["loops"]["num_tp"] >= 1, res.metrics["loops"]  # one of them is a true revisit
    gap = _loop_gap(res)
    assert gap < LOOP_GAP_BOUND, gap


def test_revisit_closes_a_verified_loop(block_on):
    _closes_loop(block_on)
    t = block_on.metrics["timing"]
    assert t["frames"] == block_on.poses.shape[0] and np.isfinite(block_on.poses.numpy()).all()
    assert t["tracking_failures"] == 0 and t["reinitialisations"] == 0


@pytest.fixture(scope="module")
def drift_on(tmp_path_factory, block):
    return _shared_run(tmp_path_factory, "drift_on", block, *NO_SEG, *ROAD_OFF)


@pytest.fixture(scope="module")
def drift_off(tmp_path_factory, block):
    return _shared_run(tmp_path_factory, "drift_off", block, *NO_SEG, *ROAD_OFF, *LOOP_OFF)


def test_loop_closure_reduces_ate(drift_on, drift_off):
    """On a map that drifts (no road plane: with the road's depth prior the block drive drifts so little, 0.16 % of
    the path without loop closure, that a loop has little left to remove) the loop takes most of the drift out."""
    on, off = _ate(drift_on), _ate(drift_off)
    assert on < LOOP_ATE_RATIO * off, (on, off)
    assert _loop_gap(drift_on) < 0.5 * _loop_gap(drift_off)


def test_loop_closure_keeps_the_default_map(block_on, block_off):
    """With the default's road prior the map barely drifts; the loop must still close the gap and not add error."""
    assert _ate(block_on) <= _ate(block_off) + 0.02, (_ate(block_on), _ate(block_off))
    assert _loop_gap(block_on) < _loop_gap(block_off)


def test_loop_test_catches_loop_closure_off(block_off, drift_off):
    """Test of the test: without loop closure, the loop test fails, on detection (the default map) and on the loop
    gap (the drifting map: the default block drive without loops drifts so little that its gap, 0.34, is within the
    bound)."""
    with pytest.raises(AssertionError):
        _closes_loop(block_off)
    gap = _loop_gap(drift_off)
    assert not gap < LOOP_GAP_BOUND, gap


# --------------------------------------------------------------------------------------- dynamic masking --
MV_FRAMES = 120  # busy_street: buses and cars up to a third of the image crossing and driving alongside
# The test runs the seed-0 busy street, where the masking matters (on moving_vehicles it barely does).  The flow
# frontend's texture term and the road plane's depth prior each protect that street on their own (masking off with
# both on: ~0.1 %), so the test of the test switches both off to see the masking alone: ATE % of the path, oracle
# labels (the masking is the frontend's eq. 4 on the labelled things), 120 frames, masking on 1.78 %, off 11.33 %;
# the bound sits between, 2.5x from each.
MV_BOUND = 4.5


def _texture_off(monkeypatch):
    """The flow frontend's texture term off: its tau is a constant of the code (pair_flow.TEXTURE_TAU), 0 = off."""
    from pvslam_plugins.frontends.flow import pair_flow

    monkeypatch.setattr(pair_flow, "TEXTURE_TAU", 0.0)


@pytest.fixture(scope="module")
def street():
    return _seq("busy_street", MV_FRAMES)


@pytest.mark.parametrize("texture_off, variant, holds", [(False, [], True), (True, ROAD_OFF, True),
                                                         (True, [*ROAD_OFF, *MASK_OFF], False)],
                         ids=["default", "texture_off", "texture_and_mask_off"])
def test_dynamic_masking_bound(tmp_path, street, monkeypatch, texture_off, variant, holds):
    """The bound on the default configuration, on the masking alone (texture term and road plane off), and its test of
    the test with the dynamic masking off too."""
    if texture_off:
        _texture_off(monkeypatch)
    res = _run(tmp_path, street, "segmenter.plugin=labels", "vps.plugin=none", *variant)  # oracle labels
    assert res.poses.shape[0] == MV_FRAMES and np.isfinite(res.poses.numpy()).all()
    ate = _ate(res)
    assert (ate < MV_BOUND) == holds, ate


# ------------------------------------------------------------------------------ a bus filling the view --
# The held-out looks' moving_vehicles seed 188: a bus 1.3-1.7x the plain size crosses and grows to about 45 % of the
# view (frames 164-188).  With the segmenter's movable things kept out of the tracking weights (TRACK_THINGS) the
# map holds; without, the tracked pose turns with the bus and the geometric masks, judged against it, let the bus
# go.  ATE % of the path, oracle labels, no loop closure: 0.133 with, 0.890 without (docs/decisions.md:
# TRACK_THINGS); the bound sits between, about 2.5x from each.
BUS_BOUND = 0.35


@pytest.fixture(scope="module")
def crossing_bus():
    from pvslam_plugins.datasets.synthetic.generator import generate

    return generate("moving_vehicles", None, seed=188, domain="heldout", progress=False)


@pytest.mark.parametrize("things_in_tracking", [True, False], ids=["default", "things_judged_only"])
def test_a_bus_filling_the_view_does_not_take_the_map(tmp_path, crossing_bus, monkeypatch, things_in_tracking):
    """The bound holds with the default, and fails when the tracking leans on movable things until the geometry has
    judged them (the test of the test)."""
    from pvslam_plugins.frontends.flow import dynamic_masking

    monkeypatch.setattr(dynamic_masking, "TRACK_THINGS", things_in_tracking)
    res = _run(tmp_path, crossing_bus, "segmenter.plugin=labels", "vps.plugin=none", *LOOP_OFF)
    assert np.isfinite(res.poses.numpy()).all()
    ate = _ate(res)
    assert (ate < BUS_BOUND) == things_in_tracking, ate


# ------------------------------------------------------------------------------- no ground truth leaks in --
class _NoGroundTruth:
    """The synthetic sequence with every ground-truth field stripped from the frames and the sequence info."""

    def __init__(self, cfg):
        import torch

        from pvslam_core.interfaces import BuildContext
        from pvslam_plugins.datasets.synthetic.config import SyntheticConfig
        from pvslam_plugins.datasets.synthetic.reader import make_reader

        self.inner = make_reader(SyntheticConfig(path=cfg.path), BuildContext(device=torch.device("cpu")))

    def info(self):
        from dataclasses import replace

        return replace(self.inner.info(), categories=(), has_gt_pose=False, has_gt_depth=False,
                       has_gt_panoptic=False, loop_pairs=None)

    def __iter__(self):
        for f in self.inner:
            f.gt_pose = f.gt_depth = f.gt_panoptic = f.gt_dynamic = None
            yield f


def _no_gt_registry():
    from pvslam_core.config_base import PluginConfig
    from pvslam_core.interfaces import DatasetReader
    from pvslam_core.registry import build_registry, hookimpl

    class Cfg(PluginConfig):
        path: str

    class Reader(_NoGroundTruth, DatasetReader):
        pass

    class Plugin:
        @staticmethod
        @hookimpl
        def register_datasets(register):
            register("no_gt", lambda c, ctx: Reader(c), Cfg, description="test-only")

    return build_registry(extra_modules=(Plugin,))


def test_estimate_does_not_depend_on_ground_truth(tmp_path, block, block_on):
    """The same frames with and without ground truth give bit-identical trajectories: nothing in estimation reads
    ground truth (the oracle segmenter, which does by design, is off).  On driving_block, so tracking, BA, loop
    detection, verification and the loop BA / pose graph are all covered."""
    without = _run(tmp_path, block, "dataset.plugin=no_gt", *NO_SEG, registry=_no_gt_registry())
    assert "ate" not in without.metrics and "loops" not in without.metrics  # really no ground truth
    assert not (Path(without.run_dir) / "groundtruth.txt").exists()
    assert "ate" in block_on.metrics and block_on.loops  # ... and the reference run had it, and closed loops
    assert without.poses.shape == block_on.poses.shape and without.poses.shape[1] == 7
    assert _same(without.poses, block_on.poses)
    assert _same(without.keyframe_indices, block_on.keyframe_indices)
    assert without.loops == block_on.loops  # the same closures (frames, keyframes, scores, inliers)


def _same(a, b) -> bool:
    return a.shape == b.shape and bool((a == b).all())
