"""Writes a rendered :class:`~.scenarios.Scenario` to disk in pvslam's synthetic layout.

Layout (``<root>`` is the sequence folder)::

    <root>/
      rgb/000000.png ...        8-bit RGB
      depth/000000.png ...      16-bit PNG, z-depth in metres * depth_scale, 0 = invalid/sky/out of range
      panoptic/000000.png ...   COCO panoptic PNG: id = R + 256*G + 256^2*B
      dynamic/000000.png ...    8-bit 0/255 mask of independently moving pixels
      rgb.txt, depth.txt        TUM lists: "timestamp filename"
      groundtruth.txt           TUM: "timestamp tx ty tz qx qy qz qw" (T_wc)
      calib.txt                 "fx fy cx cy" (one line)
      panoptic.json             {"categories": [{id,name,isthing,color}],
                                 "frames": [{"file":..., "segments_info": [{id, category_id, isthing}]}]}
      loops.json                {"pairs": [[i, j], ...], "criterion": "..."}
      objects.json              per-frame poses of moving objects (object-to-world, rotation about z)
      meta.json                 scenario, seed, size, fps, depth_scale, generator version

``depth_scale`` is 5000 (TUM) for indoor scenes and 256 (KITTI depth maps: 3.9 mm steps up to 256 m) for
outdoor ones, because TUM's 5000 saturates at 13.1 m; it is recorded in ``meta.json`` (and a comment line of
``depth.txt``).  Depths beyond ``65535 / depth_scale`` are written as 0 (invalid).

Everything is written into a temporary sibling folder that is renamed onto ``<root>`` at the end, so a crash
never leaves a half-written sequence behind (:mod:`.staging`: removed on an exception, Ctrl-C or SIGTERM, and by
the next writer when its process was killed outright).
"""
from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from .render import render
from .scenarios import Scenario, revisit_pairs
from .scene import CATEGORIES
from .staging import sigterm_cleans_up, sweep_stale, temp_folder

GENERATOR_VERSION = "1.1"


def quantize_depth(depth: np.ndarray, scale: float) -> np.ndarray:
    """uint16 depth PNG values: ``round(depth * scale)``, 0 where invalid or beyond the 16-bit range."""
    q = np.round(depth.astype(np.float64) * scale)
    q[(q > 65535) | ~np.isfinite(q) | (depth <= 0)] = 0
    return q.astype(np.uint16)


def encode_panoptic(ids: np.ndarray) -> np.ndarray:
    """COCO panoptic RGB (uint8 [H,W,3]) of integer ids: id = R + 256 G + 256^2 B."""
    ids = ids.astype(np.int64)
    return np.stack([ids % 256, (ids // 256) % 256, (ids // 65536) % 256], axis=-1).astype(np.uint8)


def decode_panoptic(rgb: np.ndarray) -> np.ndarray:
    rgb = rgb.astype(np.int64)
    return rgb[..., 0] + 256 * rgb[..., 1] + 65536 * rgb[..., 2]


def pose_to_tum(T: np.ndarray) -> list[float]:
    """``[tx, ty, tz, qx, qy, qz, qw]`` of a 4x4 pose (quaternion with qw >= 0)."""
    from scipy.spatial.transform import Rotation  # here: every run registers this plugin, few generate

    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return [float(x) for x in T[:3, 3]] + [float(x) for x in q]


def segments_info(ids: np.ndarray) -> list[dict]:
    out = []
    things = {c.id: c.isthing for c in CATEGORIES}
    for sid in np.unique(ids).tolist():
        if sid == 0:
            continue
        cat = int(sid) // 1000
        out.append({"id": int(sid), "category_id": cat, "isthing": bool(things.get(cat, False))})
    return out


def meta_of(sc: Scenario) -> dict:
    cam = sc.camera
    fps = 1.0 / float(sc.timestamps[1] - sc.timestamps[0]) if sc.num_frames > 1 else 0.0
    return {
        "generator": "pvslam.synthetic",
        "version": GENERATOR_VERSION,
        **sc.params,
        "fps": round(fps, 6),
        "depth_scale": sc.depth_scale,
        "camera": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width, "height": cam.height},
        "world": "z up, metres; poses are camera-to-world (x right, y down, z forward)",
        "moving_ids": sc.scene.moving_ids(),
    }


def _progress(total: int, enabled: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=not (enabled and sys.stderr.isatty()))


def write_sequence(sc: Scenario, root: Path, progress: bool = True) -> Path:
    """Render every frame of ``sc`` and write the folder ``root`` atomically; returns ``root``."""
    root = Path(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale(root.parent)
    tmp = temp_folder(root)
    with sigterm_cleans_up():
        try:
            _write_into(sc, tmp, progress)
            if root.exists() and root.is_dir() and not any(root.iterdir()):
                root.rmdir()
            os.rename(tmp, root)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return root


def _write_into(sc: Scenario, tmp: Path, progress: bool) -> None:
    for sub in ("rgb", "depth", "panoptic", "dynamic"):
        (tmp / sub).mkdir(parents=True)
    cam = sc.camera
    frames_json = []
    rgb_lines = ["# color images", f"# scenario {sc.name}", "# timestamp filename"]
    depth_lines = ["# depth maps", f"# depth_scale {sc.depth_scale:g} (PNG value per metre; 0 = invalid)",
                   "# timestamp filename"]
    gt_lines = ["# ground truth trajectory (camera-to-world T_wc)", "# timestamp tx ty tz qx qy qz qw"]
    objects = {m.pid: {"id": m.pid, "category_id": m.pid // 1000, "name": m.name, "size": list(m.size)}
               for m in sc.scene.movers}
    obj_frames = []
    with _progress(sc.num_frames, progress, f"synthetic {sc.name}") as bar:
        for i in range(sc.num_frames):
            out = render(sc.scene, i, sc.poses[i], cam)
            name = f"{i:06d}.png"
            ts = f"{sc.timestamps[i]:.6f}"
            cv2.imwrite(str(tmp / "rgb" / name), cv2.cvtColor(out.rgb, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(tmp / "depth" / name), quantize_depth(out.depth, sc.depth_scale))
            cv2.imwrite(str(tmp / "panoptic" / name), cv2.cvtColor(encode_panoptic(out.panoptic), cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(tmp / "dynamic" / name), out.dynamic.astype(np.uint8) * 255)
            rgb_lines.append(f"{ts} rgb/{name}")
            depth_lines.append(f"{ts} depth/{name}")
            gt_lines.append(ts + " " + " ".join(f"{x:.9f}" for x in pose_to_tum(sc.poses[i])))
            frames_json.append({"file": f"panoptic/{name}", "image": f"rgb/{name}", "timestamp": float(ts),
                                "segments_info": segments_info(out.panoptic)})
            if objects:
                obj_frames.append({"index": i, "timestamp": float(ts),
                                   "poses": {str(m.pid): m.pose7(i) for m in sc.scene.movers}})
            bar.update(1)
    (tmp / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (tmp / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (tmp / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    (tmp / "calib.txt").write_text(f"{cam.fx:.6f} {cam.fy:.6f} {cam.cx:.6f} {cam.cy:.6f}\n")
    cats = [{"id": c.id, "name": c.name, "isthing": c.isthing, "color": list(c.color)} for c in CATEGORIES]
    _dump(tmp / "panoptic.json", {"categories": cats, "frames": frames_json})
    pairs = revisit_pairs(sc.poses, sc.loop_radius, sc.loop_angle_deg, sc.loop_min_gap)
    crit = (f"i > j + {sc.loop_min_gap}, camera centres within {sc.loop_radius:g} m and optical axes within "
            f"{sc.loop_angle_deg:g} degrees (from the ground-truth poses)")
    _dump(tmp / "loops.json", {"pairs": [list(p) for p in pairs], "criterion": crit,
                               "radius_m": sc.loop_radius, "max_angle_deg": sc.loop_angle_deg,
                               "min_gap": sc.loop_min_gap})
    _dump(tmp / "objects.json", {"pose_layout": "[tx, ty, tz, qx, qy, qz, qw] object-to-world",
                                 "objects": list(objects.values()), "frames": obj_frames})
    _dump(tmp / "meta.json", meta_of(sc))


def _dump(path: Path, obj) -> None:
    with open(path, "w") as f:
        json.dump(obj, f, separators=(",", ":") if path.name in ("panoptic.json", "objects.json") else None,
                  indent=None if path.name in ("panoptic.json", "objects.json", "loops.json") else 1)
