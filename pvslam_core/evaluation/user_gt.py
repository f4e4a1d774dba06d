"""Ground truth a user brings to a finished run: ``pvslam eval RUN_DIR --gt FILE``.

A run of one's own footage (a video, an image folder) has no ground truth in its run directory; a trajectory
recorded beside it (motion capture, RTK, a dataset's pose file) can be given afterwards.  Two formats, told apart by
their column count:

* **TUM** (8 values a line: ``timestamp tx ty tz qx qy qz qw``, camera-to-world): associated with the run's frames
  by timestamp, as evo does; the timestamps must share the run's time base (the reader's: ``times.txt``, file names,
  the video container's clock or ``index / fps``);
* **KITTI** (12 values a line: the 3x4 row-major camera-to-world matrix, one line per frame of the input): line
  ``start + i * stride`` is the run's ``i``-th frame (``dataset.start`` / ``dataset.stride`` of the run's
  ``config.json``); the run's own timestamps are used.

The result is written as the run directory's ``groundtruth.txt`` (TUM), where ``pvslam eval``, the plots and
``pvslam export --format tum-aligned`` read it.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from pvslam_core.evaluation.trajectory import associate
from pvslam_core.outputs.trajectory_io import TrajectoryFormatError, read_kitti_poses, read_tum

__all__ = ["load_user_groundtruth", "sniff_format"]

MAX_DIFF = 0.01  # seconds: the evaluation's timestamp association (evaluate_run's max_diff)
FORMATS = {8: "tum", 12: "kitti"}


def sniff_format(path: str | os.PathLike) -> str:
    """``"tum"`` or ``"kitti"`` from the first data line's column count; an error naming the file and line else."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"ground-truth file not found: {path}")
    with open(path, encoding="utf-8-sig") as f:
        for lineno, line in enumerate(f, start=1):
            s = line.split("#", 1)[0].strip()
            if not s:
                continue
            n = len(s.replace(",", " ").split())
            if n in FORMATS:
                return FORMATS[n]
            hint = (" (EuRoC's state_groundtruth_estimate0/data.csv is the IMU's trajectory: run the EuRoC folder "
                    "itself, whose reader converts it to the camera, or convert it with `evo_traj euroc FILE "
                    "--save_as_tum`)") if n == 17 else ""
            raise TrajectoryFormatError(
                f"{path}:{lineno}: {n} values; expected 8 (TUM: timestamp tx ty tz qx qy qz qw) or 12 (KITTI: the "
                f"3x4 row-major camera-to-world matrix of each frame){hint}")
    raise TrajectoryFormatError(f"{path}: no poses (only blank or comment lines)")


def _start_stride(run_dir: Path) -> tuple[int, int]:
    """``dataset.start`` and ``dataset.stride`` of the run (0 and 1 where its config has none)."""
    try:
        ds = json.loads((run_dir / "config.json").read_text(encoding="utf-8")).get("dataset") or {}
    except (OSError, ValueError, AttributeError):
        ds = {}
    return int(ds.get("start") or 0), int(ds.get("stride") or 1)


def load_user_groundtruth(path: str | os.PathLike, run_dir: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, str]:
    """The ground truth in ``path`` for the run in ``run_dir`` as ``(timestamps [N], poses [N, 7] T_wc, what)``,
    ``what`` a line saying how it was associated.  :class:`ValueError` naming the file when it cannot describe the
    run's frames (a KITTI file shorter than the frames read, TUM timestamps that meet none of the run's)."""
    run_dir = Path(run_dir)
    est_ts, est = read_tum(run_dir / "trajectory.txt")
    kind = sniff_format(path)
    if kind == "kitti":
        poses = read_kitti_poses(path)
        start, stride = _start_stride(run_dir)
        lines = start + stride * np.arange(len(est_ts))
        if len(lines) and lines[-1] >= len(poses):
            raise ValueError(f"{path}: {len(poses)} KITTI poses, but the run read {len(est_ts)} frames (input frames "
                             f"{start} to {int(lines[-1])}, stride {stride}): not the pose file of this input")
        what = (f"{path} (KITTI poses: the run's frame i is line {start} + {stride} i)" if (start, stride) != (0, 1)
                else f"{path} (KITTI poses: one line per frame)")
        return est_ts.copy(), poses[lines], what
    ts, poses = read_tum(path)
    try:  # the evaluation's own association (evo's), so this check and the ATE agree on the pairs
        matched = associate(est_ts, est, ts, poses, MAX_DIFF)[2]["num_pairs"]
    except ValueError:  # no pair at all (or no finite pose)
        matched = 0
    if matched < 3:
        raise ValueError(f"{path}: {matched} of the run's {len(est_ts)} frames have a pose within {MAX_DIFF * 1000:g} "
                         f"ms (the run's timestamps {est_ts[0]:.3f}-{est_ts[-1]:.3f} s, the file's {ts[0]:.3f}-"
                         f"{ts[-1]:.3f} s): the two do not share a time base")
    return ts, poses, f"{path} (TUM: {matched} of {len(est_ts)} frames associated by timestamp)"
