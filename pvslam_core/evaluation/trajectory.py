"""Trajectory accuracy through evo's Python API: ATE (absolute trajectory error) and RPE (relative pose error).

Poses are pvslam's ``T_wc`` ``[tx, ty, tz, qx, qy, qz, qw]`` (numpy or torch). :func:`to_evo` is the one place in
pvslam that converts the quaternion order (ours xyzw -> evo's wxyz).

The computation follows what the evo command-line tools do, step by step, so that
``ate(..., align="sim3")`` equals ``evo_ape tum gt.txt est.txt -as`` and ``align="se3"`` equals ``... -a``:

1. time association: ``evo.core.sync.associate_trajectories(gt, est, max_diff=max_diff)`` (nearest timestamp,
   GT first, as ``evo_ape`` does);
2. alignment of the estimate onto the GT: Umeyama, ``correct_scale=True`` for ``"sim3"`` (monocular: scale is
   unobservable), ``False`` for ``"se3"``, none for ``"none"``;
3. ``evo.core.metrics.APE`` with ``PoseRelation.translation_part`` (metres), or ``metrics.RPE``.

Where evo refuses to align (a rank-deficient cross-covariance, e.g. a perfectly straight ground truth, where
the rotation about the line is not unique) the same closed-form Umeyama solution is computed here without the
rank check; the errors are still evo's APE. evo aligns in place, so everything works on freshly built copies; the caller's arrays are never modified.
Estimate rows that are not finite (frames a method did not register, NaN rows) are dropped before association
and counted in ``num_invalid_est``.
"""
from __future__ import annotations

import copy
from typing import Any, Optional, Sequence

import numpy as np

__all__ = ["to_evo", "from_evo", "associate", "ate", "rpe", "aligned_positions", "ate_from_files"]

_ALIGN_MODES = ("sim3", "se3", "none")


def _np(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.array(x, dtype=np.float64)  # always a copy


def to_evo(timestamps: Any, poses_wc: Any, name: Optional[str] = None):
    """``PoseTrajectory3D`` from timestamps ``[N]`` and T_wc poses ``[N, 7]`` (xyzw quaternion -> evo's wxyz)."""
    from evo.core.trajectory import PoseTrajectory3D

    ts = _np(timestamps).reshape(-1)
    p = _np(poses_wc)
    if p.ndim != 2 or p.shape[1] != 7:
        raise ValueError(f"to_evo: poses must be [N, 7] (tx ty tz qx qy qz qw), got shape {tuple(p.shape)}")
    if len(ts) != len(p):
        raise ValueError(f"to_evo: {len(ts)} timestamps but {len(p)} poses")
    if len(p) == 0:
        raise ValueError("to_evo: empty trajectory")
    xyz = np.ascontiguousarray(p[:, :3])
    q_wxyz = np.ascontiguousarray(p[:, [6, 3, 4, 5]])
    return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=q_wxyz, timestamps=ts, name=name)


def from_evo(traj) -> tuple[np.ndarray, np.ndarray]:
    """``(timestamps [N], poses [N, 7] xyzw)`` of an evo trajectory (inverse of :func:`to_evo`)."""
    q = np.asarray(traj.orientations_quat_wxyz, dtype=np.float64)
    poses = np.concatenate([np.asarray(traj.positions_xyz, dtype=np.float64), q[:, [1, 2, 3, 0]]], axis=1)
    ts = np.asarray(getattr(traj, "timestamps", np.arange(len(poses))), dtype=np.float64)
    return ts.copy(), poses


def _finite_rows(ts: np.ndarray, poses: np.ndarray) -> np.ndarray:
    return np.isfinite(ts) & np.all(np.isfinite(poses), axis=1) & (np.linalg.norm(poses[:, 3:], axis=1) > 1e-9)


def associate(est_ts, est_poses, gt_ts, gt_poses, max_diff: float):
    """Build evo trajectories (dropping invalid rows) and associate them in time, as ``evo_ape`` does: ``(traj_gt,
    traj_est, info)``, ``info["num_pairs"]`` the pairs matched within ``max_diff`` seconds (ValueError: none)."""
    from evo.core import sync

    ets, eps = _np(est_ts).reshape(-1), _np(est_poses)
    gts, gps = _np(gt_ts).reshape(-1), _np(gt_poses)
    if eps.ndim != 2 or eps.shape[1] != 7 or gps.ndim != 2 or gps.shape[1] != 7:
        raise ValueError(f"poses must be [N, 7]; got estimate {tuple(eps.shape)} and GT {tuple(gps.shape)}")
    if len(ets) != len(eps) or len(gts) != len(gps):
        raise ValueError("timestamps and poses differ in length")
    ok_e, ok_g = _finite_rows(ets, eps), _finite_rows(gts, gps)
    num_invalid_est = int((~ok_e).sum())
    if not ok_e.any():
        raise ValueError("the estimated trajectory has no valid (finite) pose")
    if not ok_g.any():
        raise ValueError("the ground-truth trajectory has no valid (finite) pose")
    traj_gt = to_evo(gts[ok_g], gps[ok_g], name="groundtruth")
    traj_est = to_evo(ets[ok_e], eps[ok_e], name="estimate")
    try:
        traj_gt, traj_est = sync.associate_trajectories(traj_gt, traj_est, max_diff=max_diff)
    except sync.SyncException as e:
        raise ValueError(f"no estimate/GT timestamp pairs within max_diff={max_diff} s: {e}") from None
    info = {
        "num_est": int(len(ets)),
        "num_gt": int(len(gts)),
        "num_invalid_est": num_invalid_est,
        "num_pairs": int(traj_est.num_poses),
    }
    return traj_gt, traj_est, info


def _umeyama_rank_deficient(x: np.ndarray, y: np.ndarray, with_scale: bool, align: str):
    """Umeyama (1991) least-squares similarity x -> y without evo's rank check (x, y: [n, 3])."""
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    var_x = float(np.mean(np.sum(xc**2, axis=1)))
    if var_x <= 1e-20:
        raise ValueError(f"{align} alignment impossible: the estimated positions are all identical")
    cov = yc.T @ xc / len(x)
    u, d, vt = np.linalg.svd(cov)
    sgn = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sgn[2, 2] = -1
    r = u @ sgn @ vt
    c = float(np.trace(np.diag(d) @ sgn) / var_x) if with_scale else 1.0
    t = my - c * r @ mx
    return r, t, c


def _align(traj_est, traj_gt, align: str) -> tuple[float, np.ndarray]:
    """Align ``traj_est`` (in place: pass a copy) onto ``traj_gt``; returns ``(scale, 4x4 sim3 matrix)``."""
    if align not in _ALIGN_MODES:
        raise ValueError(f"align must be one of {_ALIGN_MODES}, got {align!r}")
    if align == "none":
        return 1.0, np.eye(4)
    n = traj_est.num_poses
    if n < 3:
        raise ValueError(f"{align} alignment needs at least 3 associated poses, got {n}")
    from evo.core import geometry, lie_algebra

    with_scale = align == "sim3"
    try:
        r, t, s = traj_est.align(traj_gt, correct_scale=with_scale)
    except geometry.GeometryException:
        # evo refuses a rank-deficient cross-covariance (e.g. a perfectly straight ground truth): the rotation
        # about the line is then not unique, but Umeyama's closed form still gives a least-squares optimum.
        r, t, s = _umeyama_rank_deficient(traj_est.positions_xyz, traj_gt.positions_xyz, with_scale, align)
        if with_scale:
            traj_est.scale(s)
        traj_est.transform(lie_algebra.se3(r, t))
    m = np.eye(4)
    m[:3, :3] = s * np.asarray(r)
    m[:3, 3] = np.asarray(t)
    return float(s), m


def _ape_translation(traj_gt, traj_est):
    from evo.core import metrics

    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((traj_gt, traj_est))
    return m


def aligned_positions(
    est_ts: Any,
    est_poses: Any,
    gt_ts: Any,
    gt_poses: Any,
    align: str = "sim3",
    max_diff: float = 0.01,
) -> dict:
    """Associated + aligned positions for plots.

    Returns ``timestamps [M]`` (of the associated GT poses), ``est_xyz [M, 3]`` (aligned estimate),
    ``gt_xyz [M, 3]``, ``errors [M]`` (per-pose translation error, metres), ``scale`` and ``alignment``
    (4x4 similarity applied to the estimate).
    """
    traj_gt, traj_est, info = associate(est_ts, est_poses, gt_ts, gt_poses, max_diff)
    traj_est = copy.deepcopy(traj_est)
    scale, m = _align(traj_est, traj_gt, align)
    ape = _ape_translation(traj_gt, traj_est)
    stats = {k: float(v) for k, v in ape.get_all_statistics().items()}
    return {
        "timestamps": np.asarray(traj_gt.timestamps, dtype=np.float64).copy(),
        "est_xyz": np.asarray(traj_est.positions_xyz, dtype=np.float64).copy(),
        "gt_xyz": np.asarray(traj_gt.positions_xyz, dtype=np.float64).copy(),
        "errors": np.asarray(ape.error, dtype=np.float64).copy(),
        "scale": scale,
        "alignment": m,
        "stats": stats,
        **info,
    }


def ate(
    est_ts: Any,
    est_poses: Any,
    gt_ts: Any,
    gt_poses: Any,
    align: str = "sim3",
    max_diff: float = 0.01,
) -> dict:
    """Absolute trajectory error (translation part, metres) after ``align`` = ``"sim3"`` | ``"se3"`` | ``"none"``.

    Returns ``rmse, mean, median, std, min, max`` (evo's APE statistics), ``scale`` (Sim3 scale; 1 otherwise),
    ``num_pairs`` (associated poses), ``num_est``, ``num_gt``, ``num_invalid_est``, ``path_length`` (of the
    associated GT poses, metres), ``rmse_percent_of_path`` (100 * rmse / path_length), ``align``, ``max_diff``
    and ``alignment`` (4x4 similarity applied to the estimate, as nested lists).
    """
    r = aligned_positions(est_ts, est_poses, gt_ts, gt_poses, align=align, max_diff=max_diff)
    out = {k: r["stats"][k] for k in ("rmse", "mean", "median", "std", "min", "max")}  # evo's own statistics
    path_length = float(np.sum(np.linalg.norm(np.diff(r["gt_xyz"], axis=0), axis=1))) if len(r["gt_xyz"]) > 1 else 0.0
    out.update(
        scale=r["scale"],
        num_pairs=r["num_pairs"],
        num_est=r["num_est"],
        num_gt=r["num_gt"],
        num_invalid_est=r["num_invalid_est"],
        path_length=path_length,
        rmse_percent_of_path=(100.0 * out["rmse"] / path_length) if path_length > 0 else float("nan"),
        align=align,
        max_diff=float(max_diff),
        alignment=r["alignment"].tolist(),
    )
    return out


def ate_segments(
    est_ts: Any,
    est_poses: Any,
    gt_ts: Any,
    gt_poses: Any,
    cuts: Sequence[float],
    align: str = "sim3",
    max_diff: float = 0.01,
) -> list[dict]:
    """:func:`ate` of each part of the trajectory between the timestamps ``cuts`` (a part runs from one cut, included,
    to the next), each part aligned on its own: ``start``, ``end`` (its first and last estimated timestamps) and
    ``rmse``, ``rmse_percent_of_path``, ``scale``, ``num_pairs``, ``path_length``; or ``error`` (too few poses).

    Why: where a monocular map's scale was not observed (a turn on the spot wider than the view,
    :mod:`pvslam_core.slam.scale_gaps`) the parts on either side have scales of their own, and one Sim(3) for the
    whole trajectory charges the difference to every pose; the parts' scales say how large it was."""
    ts, poses = _np(est_ts).astype(np.float64), _np(est_poses)
    bounds = [-np.inf, *sorted(float(c) for c in cuts), np.inf]
    parts = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        m = (ts >= a) & (ts < b)
        if not m.any():
            continue
        part: dict[str, Any] = {"start": float(ts[m][0]), "end": float(ts[m][-1])}
        try:
            r = ate(ts[m], poses[m], gt_ts, gt_poses, align=align, max_diff=max_diff)
            part.update({k: r[k] for k in ("rmse", "rmse_percent_of_path", "scale", "num_pairs", "path_length")})
        except ValueError as e:
            part["error"] = str(e)
        parts.append(part)
    return parts


def rpe(
    est_ts: Any,
    est_poses: Any,
    gt_ts: Any,
    gt_poses: Any,
    delta: float = 1,
    delta_unit: str = "frames",
    align: str = "sim3",
    max_diff: float = 0.01,
    all_pairs: bool = False,
) -> dict:
    """Relative pose error over pose pairs ``delta`` apart (``delta_unit`` = frames | m | deg | rad), evo's RPE.

    The estimate is first aligned like :func:`ate` (Sim3 fixes the monocular scale of the translations).
    Returns ``trans_rmse, trans_mean, trans_median, trans_std, trans_min, trans_max`` (metres),
    ``rot_rmse, rot_mean, rot_median, rot_std, rot_min, rot_max`` (degrees), ``num_pairs`` (pose pairs used),
    ``num_poses`` (associated poses), ``scale``, ``delta``, ``delta_unit``, ``align``.
    """
    from evo.core import metrics

    units = {
        "frames": metrics.Unit.frames,
        "m": metrics.Unit.meters,
        "meters": metrics.Unit.meters,
        "deg": metrics.Unit.degrees,
        "degrees": metrics.Unit.degrees,
        "rad": metrics.Unit.radians,
        "radians": metrics.Unit.radians,
    }
    if delta_unit not in units:
        raise ValueError(f"delta_unit must be one of {sorted(units)}, got {delta_unit!r}")
    traj_gt, traj_est, info = associate(est_ts, est_poses, gt_ts, gt_poses, max_diff)
    traj_est = copy.deepcopy(traj_est)
    scale, _ = _align(traj_est, traj_gt, align)
    out: dict = {}
    for key, relation in (
        ("trans", metrics.PoseRelation.translation_part),
        ("rot", metrics.PoseRelation.rotation_angle_deg),
    ):
        m = metrics.RPE(relation, delta=delta, delta_unit=units[delta_unit], all_pairs=all_pairs)
        try:
            m.process_data((traj_gt, traj_est))
        except Exception as e:  # evo raises FilterException when no pair is `delta` apart
            raise ValueError(f"RPE with delta={delta} {delta_unit}: {e}") from None
        stats = m.get_all_statistics()
        for k in ("rmse", "mean", "median", "std", "min", "max"):
            out[f"{key}_{k}"] = float(stats[k])
        out["num_pairs"] = int(len(m.error))
    out.update(
        num_poses=info["num_pairs"],
        num_invalid_est=info["num_invalid_est"],
        scale=scale,
        delta=delta,
        delta_unit=delta_unit,
        align=align,
    )
    return out


def ate_from_files(est_path: str, gt_path: str, align: str = "sim3", max_diff: float = 0.01) -> dict:
    """:func:`ate` on two TUM files (read with :func:`pvslam_core.outputs.trajectory_io.read_tum`)."""
    from pvslam_core.outputs.trajectory_io import read_tum

    ets, eps = read_tum(est_path)
    gts, gps = read_tum(gt_path)
    return ate(ets, eps, gts, gps, align=align, max_diff=max_diff)
