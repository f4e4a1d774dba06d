"""``pvslam view RUN_DIR``: replay a finished run from its files alone (no dataset, no re-run).

Logged with the live viewer's entity paths (:mod:`pvslam_core.viz.rerun_viewer`): the camera along
``trajectory.txt`` on the "frame" timeline (with the image intrinsics from ``keyframes/keyframes.json``), each
frame's panoptic categories from ``panoptic/`` (COCO PNG + ``segments.json``), and statically the final trajectory,
the keyframes (``keyframes.txt``), the clouds (``cloud_rgb.ply``, ``cloud_panoptic.ply``) and the loop closures
(``loops.json``, drawn between the two frames' positions).  The run directory holds no input images, so there is
no RGB frame; a file that is missing is skipped and listed in the returned summary.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..types import Category, Intrinsics


def replay_run(run_dir: str | Path, viewer, max_panoptic_frames: int = 100000) -> dict[str, Any]:
    """Log ``run_dir`` to ``viewer`` (a :class:`~pvslam_core.viz.rerun_viewer.RerunViewer`); returns what was
    logged (counts) and what was missing."""
    from ..outputs.loops_io import read_loops
    from ..outputs.metrics import read_json
    from ..outputs.ply import read_ply
    from ..outputs.trajectory_io import read_tum

    run = Path(run_dir)
    traj = run / "trajectory.txt"
    if not traj.is_file():
        raise FileNotFoundError(f"{run}: no trajectory.txt: not a pvslam run directory (or the run wrote nothing)")
    summary: dict[str, Any] = {"missing": []}
    ts, poses = read_tum(traj)
    summary["frames"] = len(ts)

    kf_json = run / "keyframes" / "keyframes.json"
    if kf_json.is_file():
        k = read_json(kf_json)["intrinsics"]["image"]
        viewer.log_pinhole(Intrinsics(k["fx"], k["fy"], k["cx"], k["cy"], int(k["width"]), int(k["height"])))
    else:
        summary["missing"].append("keyframes/keyframes.json")

    panoptic = {}
    pan_dir = run / "panoptic"
    if (pan_dir / "segments.json").is_file():
        from ..outputs.panoptic_png import load_panoptic, read_segments_json

        meta = read_segments_json(pan_dir)
        cats = [Category(int(c["id"]), str(c.get("name", c["id"])), bool(c.get("isthing", 0)),
                         tuple(int(v) for v in c.get("color", (128, 128, 128)))) for c in meta["categories"]]
        viewer.log_categories(cats)
        panoptic = {a["frame_index"]: a for a in meta["annotations"][:max_panoptic_frames]}
    else:
        summary["missing"].append("panoptic/segments.json")

    from .rerun_viewer import category_map

    for i in range(len(ts)):
        viewer.set_frame(i, float(ts[i]))
        viewer.log_camera(poses[i])
        ann = panoptic.get(i)
        if ann is not None:
            seg = load_panoptic(pan_dir / ann["file_name"], ann["segments_info"])
            viewer.log_panoptic(category_map(seg))
    summary["panoptic_frames"] = len(panoptic)

    viewer.log_path("world/trajectory", poses[:, :3], static=True, color=(0, 200, 255))
    if (run / "keyframes.txt").is_file():
        _, kposes = read_tum(run / "keyframes.txt")
        viewer.log_points("world/keyframes", kposes[:, :3], np.tile(np.array([[255, 80, 0]], np.uint8),
                                                                    (len(kposes), 1)), static=True)
        viewer.log_path("world/keyframes/path", kposes[:, :3], static=True)
        summary["keyframes"] = len(kposes)
    else:
        summary["missing"].append("keyframes.txt")
    for kind in ("rgb", "panoptic"):
        ply = run / f"cloud_{kind}.ply"
        if ply.is_file():
            pts, cols, _ = read_ply(ply)
            viewer.log_points(f"world/map/{kind}/all", pts, cols, static=True)
            summary[f"cloud_{kind}_points"] = len(pts)
        else:
            summary["missing"].append(ply.name)
    if (run / "loops.json").is_file():
        pairs = [(int(lp["frame_i"]), int(lp["frame_j"])) for lp in read_loops(run / "loops.json")
                 if "frame_i" in lp and max(int(lp["frame_i"]), int(lp["frame_j"])) < len(poses)]
        segs = np.asarray([[poses[a, :3], poses[b, :3]] for a, b in pairs], np.float32).reshape(-1, 2, 3)
        viewer.log_segments("world/loops", segs, static=True)
        summary["loops"] = len(pairs)
    else:
        summary["missing"].append("loops.json")
    return summary
