"""The road plane on real frames, and where a run's scale and rotation go wrong.

    python bench/road_real.py                               # the road plane on every KITTI excerpt at 3 sizes
    python bench/road_real.py --seqs 06 --every 5 --json runs/bench/road_real.json
    python bench/road_real.py --run runs/RUN_DIR [--segment 5]   # a run's errors per segment and per frame

**Road plane** (``frontend.road``, chosen on the synthetic generator): on consecutive frame pairs of each excerpt,
read by the ``kitti`` reader at each processing size (``dataset.max_pixels``), the flow frontend's own search from
scratch (:class:`pvslam_plugins.frontends.flow.road_plane.RoadPlane`, the rotation between the views from the
ground truth, as the map would give it) and DIS (the default ``frontend.dis``), and per pair: the plane's
translation in camera heights against the ground truth's over :data:`CAMERA_HEIGHT_M` (the ratio is the scale the
road priors would hand the map), the plane's mean brightness residual over its rows against DIS's (the frontend
keeps a plane from scratch only when it is lower) and whether the plane would be kept.  A ratio that changes along
an excerpt is a scale drift the road's distance and depth priors put into the map; a kept fraction that changes
with the size is a prior that comes and goes with the size.  Two controls: the same residual ratio with both views
blurred by :data:`KEEP_BLUR_RAD` of view (one angular resolution at every size: where it agrees across sizes and
the unblurred one does not, the keep test follows the pixel count), and the plane's translation searched with the
ground normal orthogonal to the true travel direction instead of the camera's y axis (a car moves along its road:
where this reading is nearer 1, the assumed normal biases the scale).

**Run** (``--run``): a run directory's ``trajectory.txt`` against its ``groundtruth.txt`` (Sim(3) over the whole
run), per segment of ``--segment`` frames the travelled distance's ratio (estimate / truth: the local scale) and
the rotation error of the segment's relative rotation; per frame (``--frames``) the same for each step, the
keyframes marked.  Where the local scale or the rotation error jumps is where the run loses.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any, Optional

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import provenance  # noqa: E402
from bench.matrix_jobs import KITTI  # noqa: E402

CAMERA_HEIGHT_M = 1.65  # KITTI's camera height above the road (the sensor setup's documentation)
# the keep test at one angular resolution: both views blurred by this Gaussian sigma (radians of view) first
KEEP_BLUR_RAD = 0.012
SIZES = {"616x184": 116000, "800x240": 196608, "native": None}  # dataset.max_pixels per processing size
FRAMES = {"00": 160, "06": 51, "01": 51}  # frames of each excerpt in ../shared/data


def _poses(frames) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth rotations [n, 3, 3] and camera centres [n, 3] (T_wc) of the frames."""
    from scipy.spatial.transform import Rotation

    q = np.stack([f.gt_pose.double().numpy() for f in frames])
    return Rotation.from_quat(q[:, 3:7]).as_matrix(), q[:, :3]


def keep_ratio(plane, g0: np.ndarray, g1: np.ndarray, dis: np.ndarray, K: np.ndarray, R: np.ndarray,
               v: np.ndarray, r0: int, blur_rad: float) -> float:
    """The plane's mean brightness residual over rows ``r0:`` over DIS's (the frontend keeps a plane found from
    scratch below 1), both views first blurred by ``blur_rad`` radians of view (0: as the frontend compares)."""
    import cv2

    if blur_rad > 0:
        g0, g1 = (cv2.GaussianBlur(g, (0, 0), blur_rad * float(K[0, 0])) for g in (g0, g1))
    cost = float(plane._costs(g1.astype(np.float32), K, v[None], plane._level(g0, K, R, 2, r0))[0])
    return cost / plane._dis_cost(g0, g1, dis, r0)[0]


def travel_normal_plane(region: float, margin: float):
    """A :class:`RoadPlane` whose search takes the ground normal ``normal`` (settable) instead of the camera's y
    axis."""
    from pvslam_plugins.frontends.flow.road_plane import RoadPlane

    class _Plane(RoadPlane):
        normal = np.array([0.0, 1.0, 0.0])

        def _level(self, g0, K, R, stride, r0):
            A, _, ref, px = super()._level(g0, K, R, stride, r0)
            P = np.linalg.inv(K) @ np.stack([px[1], px[0], np.ones(px[0].size)]).astype(np.float64)
            return A, (self.normal @ P).astype(np.float32), ref, px

    return _Plane(region, margin)


def road_pairs(seq: str, max_pixels: Optional[int], every: int) -> dict[str, Any]:
    """The road plane against the ground truth and DIS on the pairs ``(k, k + 1)``, every ``every``-th ``k``."""
    from pvslam_plugins.datasets.kitti.config import KittiConfig
    from pvslam_plugins.datasets.kitti.reader import make_reader
    from pvslam_plugins.frontends.flow.config import FlowFrontendConfig
    from pvslam_plugins.frontends.flow.pair_flow import FlowPairs
    from pvslam_plugins.frontends.flow.road_plane import RoadPlane, flow_intrinsics
    from pvslam_plugins.frontends.flow.road_prior import ROAD_MARGIN, ROAD_REGION

    kitti_log = logging.getLogger("pvslam_plugins.datasets.kitti")
    level = kitti_log.level
    kitti_log.setLevel(logging.ERROR)  # "no times.txt: 10 Hz", for this reader only
    try:
        reader = make_reader(KittiConfig(path=str(KITTI), sequence=seq, max_pixels=max_pixels))
    finally:
        kitti_log.setLevel(level)
    n = min(len(reader), FRAMES.get(seq, len(reader)))
    frames = [reader[i] for i in range(n)]
    Rwc, c = _poses(frames)
    pairs = FlowPairs(FlowFrontendConfig().dis)
    plane = RoadPlane(ROAD_REGION, ROAD_MARGIN)
    travel = travel_normal_plane(ROAD_REGION, ROAD_MARGIN)
    grays = [pairs.gray(f.image) for f in frames]
    i = frames[0].intrinsics
    K = flow_intrinsics(i.fx, i.fy, i.cx, i.cy, grays[0].shape[1] / frames[0].width,
                        grays[0].shape[0] / frames[0].height)
    rows = []
    for k in range(0, n - 1, every):
        R = Rwc[k + 1].T @ Rwc[k]  # camera k -> camera k + 1
        truth = float(np.linalg.norm(c[k + 1] - c[k])) / CAMERA_HEIGHT_M
        found = plane.search(grays[k], grays[k + 1], K, R)
        if found is None or truth <= 0:
            rows.append({"pair": k, "found": False})
            continue
        v, cost, r0 = found
        dis = pairs.flow("edge", grays[k], grays[k + 1])
        dis_cost = plane._dis_cost(grays[k], grays[k + 1], dis, r0)[0]
        fixed = keep_ratio(plane, grays[k], grays[k + 1], dis, K, R, v, r0, KEEP_BLUR_RAD)
        t = Rwc[k + 1].T @ (c[k] - c[k + 1])  # the translation in camera k + 1 (X1 = R X0 + t)
        n = np.array([0.0, 1.0, 0.0]) - t[1] * t / float(t @ t)  # the y axis, orthogonal to the travel
        travel.normal = n / np.linalg.norm(n)
        on_road = travel.search(grays[k], grays[k + 1], K, R)
        rows.append({"pair": k, "found": True, "ratio": float(np.linalg.norm(v)) / truth, "cost": float(cost),
                     "dis_cost": float(dis_cost), "kept": bool(cost < dis_cost), "keep_ratio_fixed": fixed,
                     "kept_fixed": bool(fixed < 1.0),
                     "ratio_travel": None if on_road is None else float(np.linalg.norm(on_road[0])) / truth})
    pairs.close()
    got = [r for r in rows if r["found"]]
    ratios = np.array([r["ratio"] for r in got])
    summary = {"size": f"{frames[0].width}x{frames[0].height}", "pairs": len(rows)}
    if ratios.size:
        travel_r = np.array([r["ratio_travel"] for r in got if r["ratio_travel"] is not None])
        summary.update(ratio_median=float(np.median(ratios)), ratio_p10=float(np.quantile(ratios, 0.1)),
                       ratio_p90=float(np.quantile(ratios, 0.9)), kept=float(np.mean([r["kept"] for r in got])),
                       keep_ratio_median=float(np.median([r["cost"] / r["dis_cost"] for r in got])),
                       keep_ratio_fixed_median=float(np.median([r["keep_ratio_fixed"] for r in got])),
                       kept_fixed=float(np.mean([r["kept_fixed"] for r in got])),
                       ratio_travel_median=float(np.median(travel_r)) if travel_r.size else None)
    return {"summary": summary, "pairs": rows}


def _read_tum(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.loadtxt(path, comments="#", ndmin=2)
    return a[:, 0], a[:, 1:4], a[:, 4:8]


def run_segments(run_dir: Path, segment: int) -> dict[str, Any]:
    """A run's local scale and rotation error per segment and per frame step (module docstring)."""
    from scipy.spatial.transform import Rotation

    from bench.peers.common import umeyama_sim3

    ts, est, eq = _read_tum(run_dir / "trajectory.txt")
    tg, gt, gq = _read_tum(run_dir / "groundtruth.txt")
    if len(ts) != len(tg) or not np.allclose(ts, tg, atol=1e-3):
        raise SystemExit(f"road_real: error: {run_dir}: trajectory.txt and groundtruth.txt do not pair up frame "
                         f"by frame")
    kf_path = run_dir / "keyframes.txt"
    kf_ts = _read_tum(kf_path)[0] if kf_path.exists() else np.zeros(0)
    s, Rm, t = umeyama_sim3(est, gt)
    err = np.linalg.norm((s * (Rm @ est.T)).T + t - gt, axis=1)
    Re, Rg = Rotation.from_quat(eq), Rotation.from_quat(gq)

    def span(a: int, b: int) -> dict[str, float]:
        dg = float(np.linalg.norm(gt[b] - gt[a]))
        rot = (Rg[a].inv() * Rg[b]).inv() * (Re[a].inv() * Re[b])
        return {"from": a, "to": b, "scale": s * float(np.linalg.norm(est[b] - est[a])) / max(dg, 1e-12),
                "rot_err_deg": float(np.degrees(rot.magnitude())), "ate_at_end": float(err[b])}

    n = len(ts)
    steps = [{**span(k - 1, k), "keyframe": bool(np.any(np.abs(kf_ts - ts[k]) < 1e-6))} for k in range(1, n)]
    return {"run": str(run_dir), "ate_rmse": float(np.sqrt(np.mean(err ** 2))), "frames": n,
            "keyframes": int(len(kf_ts)),
            "segments": [span(a, min(a + segment, n - 1)) for a in range(0, n - 1, segment)], "steps": steps}


def _print_run(r: dict[str, Any], frames: bool) -> None:
    print(f"{r['run']}: ATE {r['ate_rmse']:.4f} m, {r['keyframes']} keyframes / {r['frames']} frames")
    for g in r["segments"] + (r["steps"] if frames else []):
        kf = " K" if g.get("keyframe") else ""
        print(f"  {g['from']:4d}-{g['to']:<4d} scale {g['scale']:6.3f}  rotation error {g['rot_err_deg']:6.3f} deg  "
              f"ATE at end {g['ate_at_end']:.3f} m{kf}")


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seqs", nargs="+", default=list(FRAMES), help="KITTI excerpts (default: %(default)s)")
    ap.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--every", type=int, default=2, help="every n-th frame pair (default: %(default)s)")
    ap.add_argument("--run", type=Path, nargs="+", help="run directories: their errors per segment instead")
    ap.add_argument("--segment", type=int, default=5, help="frames per segment of --run (default: %(default)s)")
    ap.add_argument("--frames", action="store_true", help="with --run: every frame step too")
    ap.add_argument("--json", default=None, help="result file under runs/bench/ (with provenance)")
    args = ap.parse_args(argv)
    if args.every < 1 or args.segment < 1:
        ap.error("--every and --segment must be at least 1")
    prov = provenance.check(args.json, argv) if args.json else None
    if args.run:
        out: dict[str, Any] = {"runs": []}
        for d in args.run:
            if not (d / "trajectory.txt").exists() or not (d / "groundtruth.txt").exists():
                print(f"road_real: error: {d} has no trajectory.txt and groundtruth.txt (a run directory?)")
                return 2
            out["runs"].append(run_segments(d, args.segment))
            _print_run(out["runs"][-1], args.frames)
    else:
        if not KITTI.exists():
            print(f"road_real: error: no KITTI data at {KITTI} (set PVSLAM_KITTI)")
            return 2
        out = {"camera_height_m": CAMERA_HEIGHT_M, "every": args.every, "excerpts": {}}
        print("excerpt size      pairs  plane |v| / truth: median (p10-p90), normal orthogonal to the travel  "
              "plane / DIS residual: median, kept; at 1/83 rad: median, kept")
        for seq in args.seqs:
            for name in args.sizes:
                r = road_pairs(seq, SIZES[name], args.every)
                out["excerpts"].setdefault(seq, {})[name] = r
                m = r["summary"]
                if "ratio_median" in m:
                    tr = m["ratio_travel_median"]
                    print(f"{seq:7s} {m['size']:9s} {m['pairs']:5d}  {m['ratio_median']:.3f} ({m['ratio_p10']:.3f}-"
                          f"{m['ratio_p90']:.3f}), {'-' if tr is None else f'{tr:.3f}'}{'':34s}"
                          f"{m['keep_ratio_median']:.2f}, {m['kept']:.0%}; {m['keep_ratio_fixed_median']:.2f}, "
                          f"{m['kept_fixed']:.0%}")
                else:
                    print(f"{seq:7s} {m['size']:9s} {m['pairs']:5d}  no plane in view")
    if args.json:
        print(f"wrote {provenance.write_json(args.json, out, prov)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
