"""TUM and KITTI trajectory files: strict readers, atomic writers and an incremental :class:`TrajectoryWriter`.

Pose convention (``pvslam_core.types``): ``T_wc`` as ``[tx, ty, tz, qx, qy, qz, qw]`` (scalar-last quaternion).

* **TUM**: one pose per line, ``timestamp tx ty tz qx qy qz qw``; ``#`` comments and blank lines are skipped.
  Timestamps must be strictly increasing (evo and the dataset readers rely on it).
* **KITTI** (odometry ``poses/NN.txt``): one pose per line, the 3x4 camera-to-world matrix ``[R | t]`` row-major
  (12 numbers), no timestamps.

All writers replace the file atomically (temporary file in the same folder, then ``os.replace``), so a reader
never sees a half-written file and a run stopped by an error or Ctrl-C keeps the last flushed trajectory.
"""
from __future__ import annotations

import os
from typing import Any, Iterable, Optional

import numpy as np

from ._atomic import atomic_write_text

__all__ = [
    "TrajectoryFormatError",
    "read_tum",
    "write_tum",
    "read_kitti_poses",
    "write_kitti",
    "matrix_to_pose",
    "pose_to_matrix",
    "TrajectoryWriter",
]


class TrajectoryFormatError(ValueError):
    """A trajectory file that does not follow the format; the message names the file and the line."""


# ----------------------------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------------------------
def _as_numpy(x: Any, dtype=np.float64) -> np.ndarray:
    """numpy copy of an array-like or a torch tensor (detached, on the CPU)."""
    if hasattr(x, "detach"):  # torch.Tensor without importing torch
        x = x.detach().cpu().numpy()
    return np.array(x, dtype=dtype)


def _parse_lines(path: str, ncols: int, what: str) -> tuple[np.ndarray, list[int]]:
    """Rows of ``ncols`` floats from a text file (comments ``#`` and blank lines skipped; commas allowed)."""
    rows: list[list[float]] = []
    linenos: list[int] = []
    try:
        f = open(path, "r", encoding="utf-8-sig")
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} file not found: {path}") from None
    with f:
        for lineno, line in enumerate(f, start=1):
            s = line.split("#", 1)[0].strip()
            if not s:
                continue
            parts = s.replace(",", " ").split()
            if len(parts) != ncols:
                raise TrajectoryFormatError(
                    f"{path}:{lineno}: expected {ncols} values per line ({what}), found {len(parts)}: {line.strip()!r}"
                )
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                raise TrajectoryFormatError(f"{path}:{lineno}: not a number in {line.strip()!r}") from None
            if not all(np.isfinite(vals)):
                raise TrajectoryFormatError(f"{path}:{lineno}: non-finite value in {line.strip()!r}")
            rows.append(vals)
            linenos.append(lineno)
    arr = np.array(rows, dtype=np.float64).reshape(-1, ncols)
    return arr, linenos


def _check_quaternions(path: str, quats: np.ndarray, linenos: list[int]) -> None:
    norms = np.linalg.norm(quats, axis=-1)
    bad = np.nonzero(norms < 1e-9)[0]
    if len(bad):
        raise TrajectoryFormatError(f"{path}:{linenos[bad[0]]}: zero quaternion")


def _check_timestamps(path: str, ts: np.ndarray, linenos: Optional[list[int]] = None) -> None:
    if len(ts) < 2:
        return
    d = np.diff(ts)
    bad = np.nonzero(d <= 0)[0]
    if len(bad):
        k = int(bad[0]) + 1
        where = f"{path}:{linenos[k]}" if linenos is not None else f"{path}: pose {k}"
        kind = "duplicate" if d[k - 1] == 0 else "unsorted (decreasing)"
        raise TrajectoryFormatError(
            f"{where}: {kind} timestamp {float(ts[k])!r} after {float(ts[k - 1])!r}; timestamps must be strictly "
            "increasing"
        )


def matrix_to_pose(m: np.ndarray) -> np.ndarray:
    """``[..., 3 or 4, 4]`` (or ``[..., 3, 4]``) rigid transforms to ``[..., 7]`` poses (xyzw, qw >= 0).

    The rotation block is projected onto SO(3) (KITTI files hold slightly non-orthonormal matrices).
    """
    from scipy.spatial.transform import Rotation

    m = np.asarray(m, dtype=np.float64)
    lead = m.shape[:-2]
    r = m[..., :3, :3].reshape(-1, 3, 3)
    t = m[..., :3, 3].reshape(-1, 3)
    if len(r) == 0:
        return np.zeros(lead + (7,), dtype=np.float64)
    q = Rotation.from_matrix(r).as_quat()  # xyzw
    q = np.where(q[:, 3:4] < 0, -q, q)
    return np.concatenate([t, q], axis=-1).reshape(lead + (7,))


def pose_to_matrix(poses: np.ndarray) -> np.ndarray:
    """``[..., 7]`` poses to ``[..., 4, 4]`` matrices (the quaternion is normalised)."""
    from scipy.spatial.transform import Rotation

    p = np.asarray(poses, dtype=np.float64)
    lead = p.shape[:-1]
    flat = p.reshape(-1, 7)
    out = np.tile(np.eye(4), (len(flat), 1, 1))
    if len(flat):
        out[:, :3, :3] = Rotation.from_quat(flat[:, 3:]).as_matrix()
        out[:, :3, 3] = flat[:, :3]
    return out.reshape(lead + (4, 4))


def _validate_poses(poses: np.ndarray, what: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim == 1 and poses.shape[0] == 7:
        poses = poses[None]
    if poses.ndim != 2 or poses.shape[1] != 7:
        raise ValueError(f"{what}: poses must be [N, 7] (tx ty tz qx qy qz qw), got shape {tuple(poses.shape)}")
    if not np.all(np.isfinite(poses)):
        k = int(np.nonzero(~np.all(np.isfinite(poses), axis=1))[0][0])
        raise ValueError(f"{what}: pose {k} is not finite: {poses[k].tolist()}")
    if len(poses) and np.any(np.linalg.norm(poses[:, 3:], axis=1) < 1e-9):
        raise ValueError(f"{what}: zero quaternion")
    return poses


def _fmt(x: float) -> str:
    # repr() is the shortest string that round-trips exactly.
    return repr(float(x))


# ----------------------------------------------------------------------------------------------------------------
# TUM
# ----------------------------------------------------------------------------------------------------------------
def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``(timestamps float64 [N], poses float64 [N, 7])``.

    Raises :class:`TrajectoryFormatError` (a ``ValueError``) naming the file and line for a wrong column count,
    a non-number, a zero quaternion or unsorted / duplicate timestamps.
    """
    path = os.fspath(path)
    arr, linenos = _parse_lines(path, 8, "TUM: timestamp tx ty tz qx qy qz qw")
    ts, poses = arr[:, 0].copy(), arr[:, 1:].copy()
    _check_quaternions(path, poses[:, 3:], linenos)
    _check_timestamps(path, ts, linenos)
    return ts, poses


def _tum_text(timestamps: np.ndarray, poses: np.ndarray) -> str:
    lines = ["# timestamp tx ty tz qx qy qz qw  (T_wc, camera-to-world)\n"]
    for t, p in zip(timestamps.tolist(), poses.tolist()):
        lines.append(" ".join([_fmt(t)] + [_fmt(v) for v in p]) + "\n")
    return "".join(lines)


def write_tum(path: str | os.PathLike, timestamps: Any, poses: Any) -> None:
    """Write a TUM trajectory atomically. ``timestamps`` [N] strictly increasing, ``poses`` [N, 7] T_wc."""
    path = os.fspath(path)
    ts = _as_numpy(timestamps).reshape(-1)
    poses = _validate_poses(_as_numpy(poses), f"write_tum({path})")
    if len(ts) != len(poses):
        raise ValueError(f"write_tum({path}): {len(ts)} timestamps but {len(poses)} poses")
    if not np.all(np.isfinite(ts)):
        raise ValueError(f"write_tum({path}): non-finite timestamp")
    _check_timestamps(path, ts)
    atomic_write_text(path, _tum_text(ts, poses))


# ----------------------------------------------------------------------------------------------------------------
# KITTI
# ----------------------------------------------------------------------------------------------------------------
def read_kitti_poses(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI odometry pose file (3x4 row-major camera-to-world per line) as float64 ``[N, 7]``."""
    path = os.fspath(path)
    arr, linenos = _parse_lines(path, 12, "KITTI: 3x4 row-major [R|t]")
    m = arr.reshape(-1, 3, 4)
    det = np.linalg.det(m[:, :, :3]) if len(m) else np.zeros(0)
    bad = np.nonzero(np.abs(det - 1.0) > 1e-2)[0]
    if len(bad):
        k = int(bad[0])
        raise TrajectoryFormatError(f"{path}:{linenos[k]}: rotation block is not a rotation (det={det[k]:.6g})")
    return matrix_to_pose(m)


def _kitti_text(poses: np.ndarray) -> str:
    m = pose_to_matrix(poses)[:, :3, :].reshape(-1, 12)
    return "".join(" ".join(_fmt(v) for v in row) + "\n" for row in m.tolist())


def write_kitti(path: str | os.PathLike, poses: Any) -> None:
    """Write poses ``[N, 7]`` (T_wc) as a KITTI pose file, atomically."""
    path = os.fspath(path)
    poses = _validate_poses(_as_numpy(poses), f"write_kitti({path})")
    atomic_write_text(path, _kitti_text(poses))


# ----------------------------------------------------------------------------------------------------------------
# incremental writer
# ----------------------------------------------------------------------------------------------------------------
class TrajectoryWriter:
    """Holds a trajectory in memory and rewrites its file atomically on :meth:`flush`.

    ``append`` adds a pose, ``update`` replaces the whole trajectory (poses of past frames change after bundle
    adjustment). The file on disk is always a complete, valid trajectory: the last flushed state. Used as a
    context manager it flushes on exit, also when the block raises (the in-memory trajectory is consistent:
    ``append`` / ``update`` validate before changing it), so a run stopped by an error or Ctrl-C keeps what it
    had. ``flush_every=n`` flushes automatically after every ``n`` appends / updates (0 = only explicit flushes).
    """

    def __init__(self, path: str | os.PathLike, fmt: str = "tum", flush_every: int = 0):
        if fmt not in ("tum", "kitti"):
            raise ValueError(f"TrajectoryWriter: fmt must be 'tum' or 'kitti', got {fmt!r}")
        self.path = os.fspath(path)
        self.fmt = fmt
        self.flush_every = int(flush_every)
        self._ts: list[float] = []
        self._poses: list[np.ndarray] = []
        self._pending = 0
        self.num_flushes = 0

    def __len__(self) -> int:
        return len(self._ts)

    @property
    def timestamps(self) -> np.ndarray:
        return np.array(self._ts, dtype=np.float64)

    @property
    def poses(self) -> np.ndarray:
        return np.array(self._poses, dtype=np.float64).reshape(-1, 7)

    def append(self, timestamp: float, pose: Any) -> None:
        t = float(timestamp)
        p = _validate_poses(_as_numpy(pose).reshape(-1), f"TrajectoryWriter({self.path}).append")[0]
        if not np.isfinite(t):
            raise ValueError(f"TrajectoryWriter({self.path}).append: non-finite timestamp {t}")
        if self._ts and t <= self._ts[-1]:
            raise ValueError(
                f"TrajectoryWriter({self.path}).append: timestamp {t!r} is not after the last one "
                f"{float(self._ts[-1])!r}"
            )
        self._ts.append(t)
        self._poses.append(p)
        self._tick()

    def extend(self, timestamps: Iterable[float], poses: Any) -> None:
        ts = _as_numpy(timestamps).reshape(-1)
        ps = _validate_poses(_as_numpy(poses), f"TrajectoryWriter({self.path}).extend")
        if len(ts) != len(ps):
            raise ValueError(f"TrajectoryWriter({self.path}).extend: {len(ts)} timestamps but {len(ps)} poses")
        full = np.concatenate([np.array(self._ts, dtype=np.float64), ts])
        _check_timestamps(self.path, full)
        self._ts.extend(ts.tolist())
        self._poses.extend(list(ps))
        self._tick()

    def update(self, timestamps: Any, poses: Any) -> None:
        """Replace the whole trajectory."""
        ts = _as_numpy(timestamps).reshape(-1)
        ps = _validate_poses(_as_numpy(poses), f"TrajectoryWriter({self.path}).update")
        if len(ts) != len(ps):
            raise ValueError(f"TrajectoryWriter({self.path}).update: {len(ts)} timestamps but {len(ps)} poses")
        if not np.all(np.isfinite(ts)):
            raise ValueError(f"TrajectoryWriter({self.path}).update: non-finite timestamp")
        _check_timestamps(self.path, ts)
        self._ts = ts.tolist()
        self._poses = list(ps)
        self._tick()

    def _tick(self) -> None:
        self._pending += 1
        if self.flush_every > 0 and self._pending >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        """Rewrite the file atomically with the current trajectory."""
        ts, poses = self.timestamps, self.poses
        text = _tum_text(ts, poses) if self.fmt == "tum" else _kitti_text(poses)
        atomic_write_text(self.path, text)
        self._pending = 0
        self.num_flushes += 1

    def close(self) -> None:
        self.flush()

    def __enter__(self) -> "TrajectoryWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.flush()
        else:
            # Keep what we had; never let a failing flush hide the original exception.
            try:
                self.flush()
            except Exception:
                pass
        return False
