"""Shared helpers for the benchmark peers: sequence loading, pose conversion and Sim(3) ATE.

Input layout (pvslam's synthetic / TUM-style sequence folder)::

    <root>/rgb/000000.png ...    RGB frames
    <root>/rgb.txt               "timestamp filename" per line (TUM list; '#' comments)
    <root>/groundtruth.txt       "timestamp tx ty tz qx qy qz qw" (camera-to-world T_wc), optional
    <root>/calib.txt             "fx fy cx cy"

Poses everywhere in this package are camera-to-world ``T_wc`` as ``[tx, ty, tz, qx, qy, qz, qw]``
(Hamilton quaternion, scalar last), the convention of ``pvslam_core.types``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "Sequence",
    "load_sequence",
    "read_tum_list",
    "read_tum_trajectory",
    "pose_from_Rt_cw",
    "ate_sim3",
    "umeyama_sim3",
]


@dataclass
class Sequence:
    """A loaded sequence folder (images are not read; only their paths)."""

    root: Path
    timestamps: np.ndarray  # float64 [N]
    image_paths: list[Path]  # N absolute paths
    K: np.ndarray  # float64 [3, 3]
    intrinsics: np.ndarray  # float64 [4] fx fy cx cy
    gt_timestamps: Optional[np.ndarray] = None  # float64 [M]
    gt_poses: Optional[np.ndarray] = None  # float64 [M, 7] T_wc

    def __len__(self) -> int:
        return len(self.image_paths)


def _data_lines(path: Path):
    with open(path, "r", encoding="utf-8") as fh:
        for lineno, raw in enumerate(fh, 1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            yield lineno, line.replace(",", " ").split()


def read_tum_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read a TUM image list ``timestamp filename`` -> (timestamps float64 [N], filenames)."""
    ts, names = [], []
    for lineno, parts in _data_lines(Path(path)):
        if len(parts) < 2:
            raise ValueError(f"{path}:{lineno}: expected 'timestamp filename', got {parts!r}")
        ts.append(float(parts[0]))
        names.append(parts[1])
    return np.asarray(ts, dtype=np.float64), names


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory ``timestamp tx ty tz qx qy qz qw`` -> (ts [N], poses [N, 7])."""
    rows = []
    for lineno, parts in _data_lines(Path(path)):
        if len(parts) != 8:
            raise ValueError(f"{path}:{lineno}: expected 8 columns, got {len(parts)}")
        rows.append([float(p) for p in parts])
    arr = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    return arr[:, 0].copy(), arr[:, 1:].copy()


def load_sequence(seq_dir, max_frames: Optional[int] = None) -> Sequence:
    """Load timestamps, image paths, intrinsics ``K`` and (if present) ground truth of a sequence folder.

    ``max_frames`` keeps only the first frames of the image list (ground truth is kept whole; the ATE
    associates by timestamp).
    """
    root = Path(seq_dir).resolve()
    if not (root / "rgb.txt").is_file():
        raise FileNotFoundError(f"{root}: no rgb.txt (expected a TUM-style sequence folder)")
    ts, names = read_tum_list(root / "rgb.txt")
    if max_frames is not None:
        ts, names = ts[:max_frames], names[:max_frames]
    paths = [root / n for n in names]
    calib_path = root / "calib.txt"
    if not calib_path.is_file():
        raise FileNotFoundError(f"{root}: no calib.txt ('fx fy cx cy')")
    vals = [float(v) for v in calib_path.read_text().replace(",", " ").split()]
    if len(vals) < 4:
        raise ValueError(f"{calib_path}: expected 'fx fy cx cy', got {vals}")
    fx, fy, cx, cy = vals[:4]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)
    gt_ts = gt = None
    if (root / "groundtruth.txt").is_file():
        gt_ts, gt = read_tum_trajectory(root / "groundtruth.txt")
    return Sequence(root, ts, paths, K, np.array([fx, fy, cx, cy]), gt_ts, gt)


def pose_from_Rt_cw(R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """World-to-camera (R, t) -> camera-to-world ``[tx, ty, tz, qx, qy, qz, qw]``."""
    R_wc = np.asarray(R_cw, dtype=np.float64).T
    t_wc = -R_wc @ np.asarray(t_cw, dtype=np.float64).reshape(3)
    q = Rotation.from_matrix(R_wc).as_quat()  # xyzw
    return np.concatenate([t_wc, q])


# --------------------------------------------------------------------------------------------------
# ATE
# --------------------------------------------------------------------------------------------------


def umeyama_sim3(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991). src, dst: [N, 3]."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    n = src.shape[0]
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / n
    s = float(np.trace(np.diag(D) @ S) / var_s) if var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def _associate(est_ts: np.ndarray, gt_ts: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-timestamp association (each estimate to its closest GT within ``max_diff``)."""
    order = np.argsort(gt_ts)
    g = gt_ts[order]
    pos = np.clip(np.searchsorted(g, est_ts), 1, max(len(g) - 1, 1))
    left = np.clip(pos - 1, 0, len(g) - 1)
    right = np.clip(pos, 0, len(g) - 1)
    pick = np.where(np.abs(g[left] - est_ts) <= np.abs(g[right] - est_ts), left, right)
    ok = np.abs(g[pick] - est_ts) <= max_diff
    return np.nonzero(ok)[0], order[pick[ok]]


def _path_length(xyz: np.ndarray) -> float:
    if len(xyz) < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum())


def _fallback_ate(est_ts, est, gt_ts, gt, max_diff: float) -> dict:
    ie, ig = _associate(est_ts, gt_ts, max_diff)
    if len(ie) < 3:
        raise ValueError(f"ATE needs at least 3 associated poses, got {len(ie)}")
    p_est, p_gt = est[ie, :3], gt[ig, :3]
    s, R, t = umeyama_sim3(p_est, p_gt)
    err = np.linalg.norm((s * (R @ p_est.T)).T + t - p_gt, axis=1)
    rmse = float(np.sqrt(np.mean(err**2)))
    plen = _path_length(p_gt)
    return {
        "rmse": rmse,
        "mean": float(err.mean()),
        "median": float(np.median(err)),
        "std": float(err.std()),
        "min": float(err.min()),
        "max": float(err.max()),
        "scale": s,
        "num_pairs": int(len(ie)),
        "path_length": plen,
        "rmse_percent_of_path": 100.0 * rmse / plen if plen > 0 else math.nan,
    }


def ate_sim3(est_ts, est, gt_ts, gt, max_diff: float = 0.01) -> dict:
    """Absolute trajectory error after Sim(3) alignment; rows of ``est`` with any NaN are skipped.

    Uses ``pvslam_core.evaluation.trajectory.ate(..., align="sim3")`` (evo) when it is available, otherwise
    a local Umeyama alignment of the positions. The result always has ``rmse``, ``rmse_percent_of_path``,
    ``num_pairs``, ``num_valid`` (non-NaN estimates), ``num_total`` and ``backend``.
    """
    est_ts = np.asarray(est_ts, dtype=np.float64).reshape(-1)
    est = np.asarray(est, dtype=np.float64).reshape(-1, 7)
    gt_ts = np.asarray(gt_ts, dtype=np.float64).reshape(-1)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 7)
    valid = np.all(np.isfinite(est), axis=1)
    e_ts, e = est_ts[valid], est[valid].copy()
    if len(e):
        e[:, 3:] /= np.linalg.norm(e[:, 3:], axis=1, keepdims=True)
    res = None
    backend = "umeyama"
    try:
        from pvslam_core.evaluation.trajectory import ate as _pv_ate  # type: ignore
    except Exception:  # not written yet / broken import: fall back
        _pv_ate = None
    if _pv_ate is not None:
        try:
            res = dict(_pv_ate(e_ts, e, gt_ts, gt, align="sim3", max_diff=max_diff))
            backend = "pvslam_core.evaluation"
        except Exception as exc:  # keep the benchmark going; say why
            warnings.warn(f"pvslam_core.evaluation.trajectory.ate failed ({exc!r}); using local Umeyama ATE")
            res = None
    if res is None:
        res = _fallback_ate(e_ts, e, gt_ts, gt, max_diff)
    res["num_valid"] = int(valid.sum())
    res["num_total"] = int(len(valid))
    res["backend"] = backend
    return res
