"""One cell of the benchmark matrix (``bench/bench_matrix.py``): a sequence, pvslam's default pipeline on it as a
new user would run it, the textbook VO peer, a constant-velocity straight line, and optionally COLMAP.

pvslam is run through :func:`pvslam_core.api.run_config` with the default config and only the dataset changed:
synthetic sequences through the ``images`` reader (image folder + ``calib.txt`` + ``groundtruth.txt``, no labels:
``segmenter.plugin = "none"``, ``vps.plugin = "none"``), the KITTI excerpts through the ``kitti`` reader (same
components).  With ``labels`` a second run reads the synthetic folder with the ``synthetic`` reader and keeps the
default ``labels`` segmenter (oracle panoptic labels) and the ``warp_iou`` VPS.  Every pose is scored with the same
Sim(3) ATE (:func:`bench.peers.common.ate_sim3`) over all frames, placeholders included.

Per-frame state comes from wrapping :meth:`pvslam_core.pipeline.Pipeline.step` inside the worker process: the
initialisation frame is the first whose result says ``initialized``; a frame *has a pose estimate* when its
tracking did not fail and its map fragment (frames between re-initialisations) initialised at some point (frames
before the initialisation are then placed retroactively); frames of a fragment that never initialises keep
placeholder poses.
"""
from __future__ import annotations

import math
import os
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path
from typing import Optional

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
KITTI = Path(os.environ.get("PVSLAM_KITTI", ROOT.parent / "shared" / "data" / "kitti-odometry"))


# ------------------------------------------------------------------------------------------------ sequences
def synthetic_sequence(scenario: str, seed: int, frames: Optional[int], size: tuple[int, int] = (320, 240),
                       hfov_deg: Optional[float] = None) -> Path:
    """The cached synthetic folder (generated on first use; ``size`` = (width, height), 320x240 by default;
    ``hfov_deg`` the camera's horizontal field of view, None = the generator's default camera)."""
    from pvslam_plugins.datasets.synthetic.generator import ensure_cached

    return ensure_cached(scenario, num_frames=frames, seed=seed, width=size[0], height=size[1], progress=False,
                         hfov_deg=hfov_deg)


def kitti_as_tum(seq: str, out: Path) -> Path:
    """A TUM-style folder (``rgb/`` links, ``rgb.txt``, ``calib.txt``, ``groundtruth.txt``) of a KITTI excerpt,
    for the peers; timestamps from ``times.txt`` or 10 Hz like the ``kitti`` reader."""
    from scipy.spatial.transform import Rotation

    src = KITTI / "sequences" / seq
    images = sorted((src / "image_0").glob("*.png"))
    if not images:
        raise FileNotFoundError(f"{src / 'image_0'}: no images (KITTI excerpt {seq} missing)")
    times = src / "times.txt"
    ts = np.loadtxt(times).reshape(-1) if times.is_file() else np.arange(len(images)) / 10.0
    P0 = next(line for line in (src / "calib.txt").read_text().splitlines() if line.startswith("P0:"))
    P = np.array([float(v) for v in P0.split()[1:]]).reshape(3, 4)
    gt = np.loadtxt(KITTI / "poses" / f"{seq}.txt").reshape(-1, 3, 4)
    n = min(len(images), len(ts), len(gt))
    root = out / f"kitti_{seq}"
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    lines, gt_lines = [], []
    for i in range(n):
        link = root / "rgb" / images[i].name
        if not link.exists():
            link.symlink_to(images[i].resolve())
        lines.append(f"{ts[i]:.6f} rgb/{images[i].name}")
        q = Rotation.from_matrix(gt[i, :, :3]).as_quat()
        gt_lines.append(f"{ts[i]:.6f} " + " ".join(f"{v:.9f}" for v in list(gt[i, :, 3]) + list(q)))
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    (root / "calib.txt").write_text(f"{P[0, 0]} {P[1, 1]} {P[0, 2]} {P[1, 2]}\n")
    return root


def read_gt(seq_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    from bench.peers.common import read_tum_trajectory

    return read_tum_trajectory(seq_dir / "groundtruth.txt")


# KITTI's ground truth begins some sequences with a constant-velocity extrapolation instead of measured motion, which
# no camera follows; the real benchmarks score from the first measured frame
# (docs/decisions.md: MEASURED GROUND TRUTH)
EXTRAPOLATED_TOL_DEG = 0.002  # increments closer than this (deg, any axis) to the previous one repeat it
EXTRAPOLATED_MIN = 3  # ... and only a leading run of at least this many repeats is an extrapolation


def measured_from(gt: np.ndarray) -> int:
    """Index of the first frame whose ground truth is measured: 0, or the frame after a leading run of poses whose
    rotation increments repeat (``gt`` [N, 7] TUM T_wc rows ``tx ty tz qx qy qz qw``)."""
    from scipy.spatial.transform import Rotation

    gt = np.asarray(gt, np.float64).reshape(-1, 7)
    if len(gt) < EXTRAPOLATED_MIN + 2:
        return 0
    R = Rotation.from_quat(gt[:, 3:])
    inc = np.degrees((R[:-1].inv() * R[1:]).as_rotvec())  # [N-1, 3] in the camera frame
    same = np.abs(np.diff(inc, axis=0)).max(1) < EXTRAPOLATED_TOL_DEG  # [N-2]: increment k + 1 repeats k
    if same.all():  # a steady motion all along (a synthetic drive): nothing to tell apart
        return 0
    run = int(np.argmin(same))
    # increments 0..run are on the line: frames 0..run + 1; the first measured frame follows
    return 0 if run < EXTRAPOLATED_MIN else run + 2


def motion_start(gt_ts: np.ndarray, gt: np.ndarray) -> float:
    """Time of the last frame before the camera has moved (> 1 cm or > 0.5 deg from the first frame)."""
    from scipy.spatial.transform import Rotation

    d = np.linalg.norm(gt[:, :3] - gt[0, :3], axis=1)
    ang = np.degrees((Rotation.from_quat(gt[:, 3:]) * Rotation.from_quat(gt[0, 3:]).inv()).magnitude())
    moved = np.nonzero((d > 0.01) | (ang > 0.5))[0]
    return float(gt_ts[max(int(moved[0]) - 1, 0)]) if len(moved) else float(gt_ts[-1])


def ate_pct(ts, poses, gt_ts, gt) -> dict:
    from bench.peers.common import ate_sim3

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # degenerate (never initialised) trajectories fall back to Umeyama
        a = ate_sim3(ts, poses, gt_ts, gt, max_diff=0.02)
    return {"ate_m": float(a["rmse"]), "ate_pct": float(a["rmse_percent_of_path"]), "pairs": int(a["num_pairs"])}


def line_baseline(gt_ts: np.ndarray, gt: np.ndarray) -> dict:
    """A constant-velocity straight line, Sim(3)-aligned: the least-squares fit ``p(t) = a + b t`` to the GT
    positions (what a Sim(3) alignment of equally timed collinear positions can reach at best)."""
    A = np.stack([np.ones_like(gt_ts), gt_ts - gt_ts[0]], 1)
    coef, *_ = np.linalg.lstsq(A, gt[:, :3], rcond=None)
    err = np.linalg.norm(A @ coef - gt[:, :3], axis=1)
    rmse = float(np.sqrt(np.mean(err ** 2)))
    path = float(np.linalg.norm(np.diff(gt[:, :3], axis=0), axis=1).sum())
    return {"ate_m": rmse, "ate_pct": 100.0 * rmse / path if path > 0 else math.nan}


# ------------------------------------------------------------------------------------------------ pvslam
def run_pvslam(overrides: list[str], out: Path, name: str) -> dict:
    """Run the default pipeline with ``overrides``; per-frame (index, initialized, failed) recorded."""
    from pvslam_core import pipeline as pl
    from pvslam_core.api import run_config

    base = [f'run.output_dir="{out.as_posix()}"', f'run.name="{name}"', "run.progress=false", "outputs.ply=false",
            "outputs.plots=false", "outputs.panoptic_png=false"]
    record: list[tuple[int, bool, bool]] = []
    first_map: dict = {}  # the keyframes (timestamps, T_wc) when the map first initialised
    original = pl.Pipeline.step

    def step(self, frame, next_frame=None):
        r = original(self, frame, next_frame)
        record.append((int(r.frame_index), bool(r.initialized), bool(r.failed)))
        if r.initialized and not first_map and self.mapper is not None:
            g = self.mapper.graph
            first_map.update(timestamps=g.timestamps.double().cpu().numpy().copy(),
                             poses=g.poses.double().cpu().numpy().copy())
        return r

    pl.Pipeline.step = step
    try:
        res = run_config(None, overrides=base + overrides)
    finally:
        pl.Pipeline.step = original
    timing = res.metrics.get("timing", {})
    init = np.array([r[1] for r in record], bool)
    has_pose = posed_frames(init, np.array([r[2] for r in record], bool))
    first = np.nonzero(init)[0]
    return {
        "timestamps": res.timestamps.double().numpy(), "poses": res.poses.double().numpy(),
        "frames": int(timing.get("frames", len(record))), "posed": int(has_pose.sum()),
        "init_frame": int(record[first[0]][0]) if len(first) else None,
        "reinits": int(timing.get("reinitialisations", 0)), "failures": int(timing.get("tracking_failures", 0)),
        "fps": float(timing.get("fps", math.nan)), "seconds": float(timing.get("seconds", math.nan)),
        "keyframes": int(timing.get("keyframes", 0)), "loops": len(res.loops), "run_dir": res.run_dir,
        "own_ate_pct": float(res.metrics.get("ate", {}).get("rmse_percent_of_path", math.nan)),
        "first_map": first_map or None,
    }


def init_errors(kf_ts: np.ndarray, kf_poses: np.ndarray, gt_ts: np.ndarray, gt: np.ndarray) -> dict:
    """How right the map was when it first initialised: the motion from its first keyframe to its last (``kf_ts``
    [K], ``kf_poses`` [K, 7] T_wc) against the ground truth's (TUM rows [N, 7], nearest timestamps within 20 ms):
    the rotation error and the angle between the translation directions (degrees; the scale is free), both in the
    first keyframe's frame.  A wrong two-view motion (the rotation / translation ambiguity of a narrow or forward
    view) shows here before the window BA's later drift hides where it came from."""
    from scipy.spatial.transform import Rotation

    from bench.peers.common import _associate

    ends = np.asarray([kf_ts[0], kf_ts[-1]], dtype=np.float64) if len(kf_ts) >= 2 else np.zeros(0)
    found, at = _associate(ends, gt_ts, max_diff=0.02)
    if len(found) < 2:
        return {"init_rot_err_deg": None, "init_t_err_deg": None}
    a, b = gt[at[0]], gt[at[1]]
    rel = {}
    for key, (pa, pb) in (("est", (kf_poses[0], kf_poses[-1])), ("gt", (a, b))):
        Ra, Rb = Rotation.from_quat(pa[3:7]), Rotation.from_quat(pb[3:7])
        rel[key] = (Ra.inv() * Rb, Ra.inv().apply(pb[:3] - pa[:3]))  # b in a's frame: rotation, centre
    rot = float(np.degrees((rel["gt"][0].inv() * rel["est"][0]).magnitude()))
    te, tg = rel["est"][1], rel["gt"][1]
    n = float(np.linalg.norm(te) * np.linalg.norm(tg))
    t_err = float(np.degrees(np.arccos(np.clip(te @ tg / n, -1.0, 1.0)))) if n > 0 else None
    return {"init_rot_err_deg": rot, "init_t_err_deg": t_err}


def posed_frames(initialized: np.ndarray, failed: np.ndarray) -> np.ndarray:
    """Which frames have a pose estimate [N] bool, from the per-frame ``initialized`` / ``failed`` flags [N].

    A map fragment starts at frame 0 and wherever ``initialized`` drops from True to False (a re-initialisation);
    a fragment that initialises places its earlier frames retroactively, one that never does leaves placeholders.
    Frames whose tracking failed carry a prediction, not an estimate.
    """
    init = np.asarray(initialized, bool)
    if len(init) == 0:
        return np.zeros(0, bool)
    frag = np.cumsum(np.concatenate([[0], (~init[1:] & init[:-1]).astype(np.int64)]))
    frag_ok = np.zeros(int(frag[-1]) + 1, bool)
    np.logical_or.at(frag_ok, frag, init)
    return frag_ok[frag] & ~np.asarray(failed, bool)


def pvslam_overrides(kind: str, seq_dir: Path, fps: float, frames: Optional[int], labels: bool) -> list[str]:
    """Dataset overrides: ``kind`` is ``synthetic`` or ``kitti_NN``."""
    cap = [f"run.max_frames={frames}"] if frames else []
    if kind.startswith("kitti_"):
        return [f'dataset.plugin="kitti"', f'dataset.path="{KITTI.as_posix()}"', f'dataset.sequence="{kind[6:]}"',
                "segmenter.plugin=none", "vps.plugin=none"] + cap
    if labels:  # the default pipeline as `pvslam run` has it: synthetic reader, oracle labels, VPS
        return ['dataset.plugin="synthetic"', f'dataset.path="{seq_dir.as_posix()}"'] + cap
    return ['dataset.plugin="images"', f'dataset.path="{(seq_dir / "rgb").as_posix()}"',
            f'dataset.calib="{(seq_dir / "calib.txt").as_posix()}"', f"dataset.fps={fps}",
            f'dataset.groundtruth="{(seq_dir / "groundtruth.txt").as_posix()}"',
            "segmenter.plugin=none", "vps.plugin=none"] + cap


# ------------------------------------------------------------------------------------------------ one cell
def run_cell(job: dict) -> dict:
    """Everything for one (scenario, seed): returns a JSON-able row (errors are recorded, not raised)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import cv2

    cv2.setNumThreads(1)
    scenario, seed, frames = job["scenario"], job["seed"], job.get("frames")
    out = Path(job["out"])
    row: dict = {"scenario": scenario, "seed": seed, "set": job.get("set")}
    t0 = time.perf_counter()
    try:
        if scenario.startswith("kitti_"):
            seq_dir = kitti_as_tum(scenario[6:], out / "kitti")
            fps = 10.0
        else:
            seq_dir = synthetic_sequence(scenario, seed, frames, tuple(job.get("size") or (320, 240)),
                                         job.get("hfov_deg"))
            if job.get("exposure"):  # a copy whose images follow a camera's auto-exposure, for every method
                from pvslam_plugins.datasets.synthetic.exposure import exposure_copy

                seq_dir = exposure_copy(seq_dir, out / "exposure" / f"{scenario}-s{seed}-{time.time_ns()}")
            import json

            fps = float(json.loads((seq_dir / "meta.json").read_text())["fps"])
    except Exception as exc:  # noqa: BLE001 - recorded in the row
        row["error"] = f"sequence: {type(exc).__name__}: {exc}"
        return row
    row["generate_s"] = time.perf_counter() - t0
    gt_ts, gt = read_gt(seq_dir)
    if frames:
        gt_ts, gt = gt_ts[:frames], gt[:frames]
    row["frames"] = int(len(gt_ts))
    row["path_m"] = float(np.linalg.norm(np.diff(gt[:, :3], axis=0), axis=1).sum())
    row["fps_data"] = fps
    t_motion = motion_start(gt_ts, gt)
    row["line"] = line_baseline(gt_ts, gt)
    variants = [("pvslam", False)] + ([("labels", True)] if job.get("labels") and not scenario.startswith("kitti_")
                                      else [])
    for key, labels in variants:
        try:
            kind = scenario if scenario.startswith("kitti_") else "synthetic"
            r = run_pvslam(pvslam_overrides(kind, seq_dir, fps, frames, labels) + list(job.get("overrides") or ()),
                           out / "runs",
                           f"{scenario}-s{seed}-{key}")
            r.update(ate_pct(r.pop("timestamps"), r.pop("poses"), gt_ts, gt))
            fm = r.pop("first_map")
            if fm is not None:
                r.update(init_errors(fm["timestamps"], fm["poses"], gt_ts, gt))
            i = r["init_frame"]
            r["init_s"] = None if i is None else float(gt_ts[min(i, len(gt_ts) - 1)] - t_motion)
            row[key] = r
        except Exception as exc:  # noqa: BLE001
            row[key] = {"error": f"{type(exc).__name__}: {exc}", "trace": traceback.format_exc()[-2000:]}
    try:
        from bench.peers.textbook_vo import run_textbook_vo

        vo = run_textbook_vo(seq_dir, max_frames=frames)
        row["vo"] = {**ate_pct(vo["timestamps"], vo["poses"], gt_ts, gt), "fps": float(vo["fps"]),
                     "init_frame": int(vo["stats"].get("init_frame", -1))}
    except Exception as exc:  # noqa: BLE001
        row["vo"] = {"error": f"{type(exc).__name__}: {exc}"}
    if job.get("colmap"):
        try:
            from bench.peers.colmap_peer import run_colmap

            with tempfile.TemporaryDirectory() as work:
                cm = run_colmap(seq_dir, Path(work), max_frames=frames, num_threads=job.get("colmap_threads", -1))
            row["colmap"] = {"seconds": float(cm["seconds"]), "registered": int(cm["num_registered"])}
            if cm["num_registered"] >= 3:  # else no model: no ATE
                row["colmap"].update(ate_pct(cm["timestamps"], cm["poses"], gt_ts, gt))
        except Exception as exc:  # noqa: BLE001
            row["colmap"] = {"error": f"{type(exc).__name__}: {exc}"}
    row["cell_s"] = time.perf_counter() - t0
    return row
