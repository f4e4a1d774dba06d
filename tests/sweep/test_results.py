"""The results table on hand-made cell folders: mean ± std over seeds (checked against numpy), best variant,
failed cells, CSV/Markdown and plots; nothing is run here."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from pvslam_core.outputs.trajectory_io import write_tum
from pvslam_core.sweep.results import write_results
from pvslam_core.sweep.spec import load_sweep

from sweep_helpers import sweep_text

ATE = {  # (sequence, seed, variant) -> ATE RMSE
    ("driving_loop", 0, "online_ba+loop"): 0.10, ("driving_loop", 1, "online_ba+loop"): 0.14,
    ("driving_loop", 2, "online_ba+loop"): 0.12,
    ("driving_loop", 0, "offline_ba"): 0.30, ("driving_loop", 1, "offline_ba"): 0.20,
    ("moving_vehicles", 0, "online_ba+loop"): 0.50, ("moving_vehicles", 1, "online_ba+loop"): 0.70,
    ("moving_vehicles", 0, "offline_ba"): 0.40, ("moving_vehicles", 1, "offline_ba"): 0.44,
    ("moving_vehicles", 2, "offline_ba"): 0.42,
}
FAILED = ("driving_loop", 2, "offline_ba")  # the one cell that failed
# moving_vehicles / seed 2 / online_ba+loop: never ran (no folder)


def _traj(n=30, noise=0.0, seed=0):
    t = np.linspace(0, 3, n)
    xyz = np.stack([10 * np.cos(t), np.zeros(n), 6 * np.sin(t)], 1) + noise * np.random.default_rng(seed).normal(size=(n, 3))
    q = np.tile([0, 0, 0, 1.0], (n, 1))
    return t, np.concatenate([xyz, q], 1)


@pytest.fixture
def sweep_dirs(tmp_path):
    cfg = tmp_path / "s.toml"
    cfg.write_text(sweep_text(tmp_path / "out", scenarios=("driving_loop", "moving_vehicles"), seeds=(0, 1, 2)))
    plan = load_sweep(cfg)
    root = plan.directory / "cells"
    for c in plan.cells:
        k = (c.sequence, c.seed, c.variant)
        d = root / c.name
        if k == FAILED:
            d.mkdir(parents=True)
            (d / "failed.json").write_text(json.dumps({"status": "failed", "key": c.key, "error": "ValueError: boom"}))
            continue
        if k not in ATE:
            continue
        d.mkdir(parents=True)
        m = {"timing": {"fps": 10.0 + c.seed, "keyframes": 5}, "ate": {"rmse": ATE[k], "rmse_percent_of_path": ATE[k] * 2,
                                                                        "align": "sim3"},
             "rpe": {"trans_rmse": 0.01, "rot_rmse": 0.1}, "loops": {"precision": None, "recall": 1.0, "num_detected": 2},
             "panoptic": {"pq": 0.9, "vpq": 0.8}}
        (d / "metrics.json").write_text(json.dumps(m))
        ts, gt = _traj()
        _, est = _traj(noise=ATE[k], seed=c.seed)
        write_tum(d / "groundtruth.txt", ts, gt)
        write_tum(d / "trajectory.txt", ts, est)
        (d / "done.json").write_text(json.dumps({"status": "done", "key": c.key, "seconds": 3.0}))
    return plan, root


def test_table_stats_best_and_files(sweep_dirs, tmp_path):
    plan, root = sweep_dirs
    paths = write_results(plan, root, tmp_path / "res")
    cells = pd.read_csv(paths["cells_csv"])
    assert len(cells) == 12 and (cells["status"] == "done").sum() == 10
    assert (cells["status"] == "failed").sum() == 1 and (cells["status"] == "pending").sum() == 1
    assert cells.loc[cells["status"] == "failed", "error"].iloc[0] == "ValueError: boom"
    s = pd.read_csv(paths["summary_csv"]).set_index(["sequence", "variant"])
    for (seq, var), row in s.iterrows():
        vals = np.array([v for (q, _, w), v in ATE.items() if q == seq and w == var])
        assert row["ate_rmse_mean"] == pytest.approx(vals.mean())
        assert row["ate_rmse_std"] == pytest.approx(vals.std(ddof=1))
        assert row["seeds_done"] == len(vals)
    assert s.loc[("driving_loop", "offline_ba"), "seeds_failed"] == 1
    assert s.loc[("driving_loop", "online_ba+loop"), "best"] and not s.loc[("driving_loop", "offline_ba"), "best"]
    assert s.loc[("moving_vehicles", "offline_ba"), "best"]
    assert np.isnan(s.loc[("driving_loop", "online_ba+loop"), "loop_precision_mean"])  # null -> missing, not 0
    md = paths["markdown"].read_text()
    assert "**online_ba+loop** (best)" in md and "0.1200 ± 0.0200" in md and "failed: ValueError: boom" in md
    assert "2/3 (1 failed)" in md
    for key in ("ate_plot", "trajectories_driving_loop", "trajectories_moving_vehicles"):
        assert paths[key].stat().st_size > 5000 and paths[key].read_bytes()[:4] == b"\x89PNG"
