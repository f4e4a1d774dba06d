"""The rerun viewer, headless: a live run and a replayed run directory are written to .rrd recordings and read
back (entity by entity, values compared with the run).  Skipped where rerun-sdk is not installed (it is in the
`test` extra, so CI runs these)."""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun")

from pvslam_core.api import run_config  # noqa: E402
from pvslam_core.cli import main  # noqa: E402
from pvslam_core.outputs.ply import read_ply  # noqa: E402
from pvslam_core.outputs.trajectory_io import read_tum  # noqa: E402
from pvslam_core.viz.rerun_viewer import RerunViewer  # noqa: E402

LOOPS = ['loop.plugin="every_kf"', "dataset.frames=16"]


@pytest.fixture
def every_loop(monkeypatch):
    """No suppression around accepted loops, so that the fake detector's every candidate closes one."""
    import pvslam_core.slam.loops as loops

    monkeypatch.setattr(loops, "NMS_KEYFRAMES", 0)


def read_rrd(path: Path) -> dict[str, list[dict]]:
    """Every logged row of a recording, by entity path (rows sorted by the "frame" timeline; static rows first)."""
    try:
        from rerun.chunk import RrdReader
    except ImportError:  # pragma: no cover - rerun < 0.41 has no chunk reader
        pytest.skip("this rerun-sdk cannot read .rrd files back (rerun.chunk.RrdReader)")
    rows: dict[str, list[dict]] = defaultdict(list)
    for chunk in RrdReader(str(path)).stream():
        rb = chunk.to_record_batch()
        cols = {n: rb.column(n).to_pylist() for n in rb.schema.names if n != "rerun.controls.RowId"}
        for k in range(rb.num_rows):
            rows[chunk.entity_path].append({n: v[k] for n, v in cols.items()})
    for r in rows.values():
        r.sort(key=lambda row: -1 if row.get("frame") is None else row["frame"])
    return rows


class Watching(RerunViewer):
    """The viewer, remembering each frame's pose as the pipeline reported it."""

    def on_frame(self, frame, result, panoptic):
        self.seen = getattr(self, "seen", []) + [result.pose.numpy().copy()]
        super().on_frame(frame, result, panoptic)

    def on_finish(self, result, keyframes):
        self.last_snapshot = keyframes
        super().on_finish(result, keyframes)


def test_a_live_run_is_recorded(fake_registry, fake_config_file, tmp_path, every_loop):
    viewer = Watching(spawn=False, save=tmp_path / "live.rrd")
    res = run_config(fake_config_file, overrides=LOOPS, registry=fake_registry, observer=viewer)
    viewer.close()
    rows = read_rrd(tmp_path / "live.rrd")
    cams = rows["/world/camera"]
    assert [r["frame"] for r in cams] == list(range(16))
    got = np.array([r["Transform3D:translation"][0] for r in cams])
    assert np.allclose(got, np.array(viewer.seen)[:, :3], atol=1e-6)  # the camera path, frame by frame
    quat = np.array([r["Transform3D:quaternion"][0] for r in cams])
    assert np.allclose(quat, np.array(viewer.seen)[:, 3:], atol=1e-6)
    assert len(rows["/world/camera/image/rgb"]) == 16 and len(rows["/world/camera/image/panoptic"]) == 16
    assert "/world/camera/image" in rows  # the pinhole
    # the growing cloud: one entity per keyframe (stable id), coloured by RGB and by panoptic class
    snap = viewer.last_snapshot
    kf_entities = {p for p in rows if p.startswith("/world/map/rgb/kf_")}
    pan_entities = {p for p in rows if p.startswith("/world/map/panoptic/kf_")}
    assert {f"/world/map/rgb/kf_{i}" for i in snap.ids.tolist()} <= kf_entities
    assert {p.replace("/rgb/", "/panoptic/") for p in kf_entities} == pan_entities
    pts = rows[sorted(kf_entities)[0]][-1]
    assert len(pts["Points3D:positions"]) == len(pts["Points3D:colors"]) > 0
    # one loop edge per accepted loop, between the two keyframes' final positions
    where = {int(i): p for i, p in zip(snap.ids.tolist(), snap.poses[:, :3].numpy())}
    want = [np.stack([where[lp.kf_i], where[lp.kf_j]]) for lp in res.loops]
    loops = rows["/world/loops"][-1]["LineStrips3D:strips"]
    assert len(loops) == len(res.loops) > 0 and np.allclose(np.array(loops), np.array(want), atol=1e-5)
    # the final trajectory after the last BA
    traj = np.array(rows["/world/trajectory"][-1]["LineStrips3D:strips"][0])
    assert np.allclose(traj, res.poses[:, :3].numpy(), atol=1e-5)
    assert any("ViewCoordinates:xyz" in r for r in rows["/world"])  # OpenCV axes: right, down, forward


def test_memory_recording_without_sinks(fake_registry, fake_config_file, tmp_path):
    viewer = RerunViewer(spawn=False)
    run_config(fake_config_file, registry=fake_registry, observer=viewer)
    data = viewer.memory_bytes()
    (tmp_path / "mem.rrd").write_bytes(data)
    rows = read_rrd(tmp_path / "mem.rrd")
    assert len(rows["/world/camera"]) == 12


def test_cli_view_replays_a_run_directory(fake_registry, fake_config_file, tmp_path, monkeypatch, capsys, every_loop):
    res = run_config(fake_config_file, overrides=LOOPS, registry=fake_registry)
    run = Path(res.run_dir)
    out = tmp_path / "replay.rrd"
    assert main(["view", str(run), "--save", str(out)]) == 0
    said = capsys.readouterr().out
    assert "replayed: frames 16" in said and f"recording: {out}" in said
    rows = read_rrd(out)
    ts, poses = read_tum(run / "trajectory.txt")
    cams = rows["/world/camera"]
    assert [r["frame"] for r in cams] == list(range(16))
    assert np.allclose([r["Transform3D:translation"][0] for r in cams], poses[:, :3], atol=1e-6)
    pts, cols, _ = read_ply(run / "cloud_rgb.ply")
    cloud = rows["/world/map/rgb/all"][0]
    assert np.allclose(cloud["Points3D:positions"], pts)
    rgba = np.array(cloud["Points3D:colors"], np.uint64)  # rerun packs colours as 0xRRGGBBAA
    assert np.array_equal(np.stack([rgba >> 24, (rgba >> 16) & 255, (rgba >> 8) & 255], 1), cols)
    meta = json.loads((run / "panoptic" / "segments.json").read_text())
    assert len(rows["/world/camera/image/panoptic"]) == len(meta["annotations"]) == 16
    labels = {c["class_id"]: c["class_description"]["info"]["label"]
              for r in rows["/world"] if "AnnotationContext:context" in r for c in r["AnnotationContext:context"][0]}
    assert labels == {int(c["id"]): c["name"] for c in meta["categories"]}  # the class colours/names of the overlay
    loops = json.loads((run / "loops.json").read_text())["loops"]
    assert len(rows["/world/loops"][0]["LineStrips3D:strips"]) == len(loops) > 0
    assert "/world/camera/image" in rows


def test_cli_run_with_viz_save(fake_registry, fake_config_file, tmp_path, monkeypatch, capsys):
    from pvslam_core import registry as r

    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    out = tmp_path / "cli.rrd"
    assert main(["run", "-c", str(fake_config_file), "--viz-save", str(out), "-q"]) == 0
    assert f"viewer recording: {out}" in capsys.readouterr().err
    assert len(read_rrd(out)["/world/camera"]) == 12
