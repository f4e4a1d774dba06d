"""A KITTI, an EuRoC and a TUM folder and a video each run right in one line, `pvslam run PATH [--calib FILE]`,
with their own calibration file; `--config FILE` keeps its [dataset] keys that the detected reader has."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from own_data import CX, CY, FX, N, W, own_data, own_layouts
from pvslam_core.api import path_overrides, run_path
from pvslam_core.cli import main
from pvslam_core.config import ConfigError, load_config


@pytest.fixture(scope="module")
def layouts(tmp_path_factory):
    return own_layouts(tmp_path_factory)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return own_data(tmp_path_factory)


def the_run(out: Path) -> tuple[Path, dict, dict]:
    (run,) = [d for d in out.iterdir() if d.is_dir()]
    return run, json.loads((run / "config.json").read_text()), json.loads((run / "metrics.json").read_text())


@pytest.mark.parametrize("kind, calib, plugin, said", [
    # a sequence folder under a parent not named `sequences`, its own calib.txt; times.txt has 5 rows too many
    ("kitti", None, "kitti", "KITTI odometry sequence my_drive (image_0)"),
    ("euroc", None, "euroc", "EuRoC MAV sequence euroc_mine (cam0)"),  # sensor.yaml
    ("tum", "orb", "tum", "TUM RGB-D sequence tum_mine"),  # ORB-SLAM's YAML, as TUM users have it
    ("video", "kitti_calib", "video", "video file clip.avi"),  # KITTI's P0..P3 rows for a video
])
def test_each_layout_runs_in_one_line_with_its_own_calibration(layouts, tmp_path, capsys, kind, calib, plugin, said):
    out = tmp_path / "runs"
    argv = ["run", str(layouts[kind])] + (["--calib", str(layouts[calib])] if calib else [])
    code = main(argv + ["--output-dir", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert f"pvslam: input: {said}" in err and f"({plugin} reader)" in err
    run, cfg, metrics = the_run(out)
    assert cfg["dataset"]["plugin"] == plugin
    assert metrics["tracking"]["initialized"] and metrics["timing"]["frames"] == N, err
    log = (run / "log.txt").read_text()
    if kind == "kitti":
        assert "35 timestamps for 30 images" in log and "using the first 30" in log
    if kind == "video":
        assert "KITTI projection row P0 (the default camera)" in err  # which row was taken, on the console


def test_the_intrinsics_each_layout_gives(layouts):
    """Detection and the intrinsics read from each layout's own calibration file (no run)."""
    from pvslam_core.datasets.detect import dataset_section
    from pvslam_core.registry import get_registry

    reg = get_registry()
    for kind, calib in (("kitti", None), ("euroc", None), ("tum", "orb"), ("video", "kitti_calib")):
        det = dataset_section(layouts[kind], layouts[calib] if calib else None)
        spec = reg.get("dataset", det.plugin)
        k = spec.factory(spec.config_model(**det.options, crop_multiple=1), None).info().intrinsics
        assert (k.fx, k.fy, k.cx, k.cy, k.width) == pytest.approx((FX, FX, CX, CY, W)), kind


# ------------------------------------------------------------------------------------ --config with a PATH --
def kitti_config(tmp_path: Path, extra: str = "") -> Path:
    p = tmp_path / "kitti.toml"
    p.write_text('[dataset]\nplugin = "kitti"\npath = "/nowhere"\nsequence = "06"\ncamera = "image_2"\n'
                 f'resize = [128, 96]\nend = 16\n{extra}[run]\noutput_dir = {json.dumps(str(tmp_path / "runs"))}\n'
                 'progress = false\n')
    return p


def test_cli_path_with_a_config_keeps_its_dataset_keys(data, tmp_path, capsys):
    """The config's resize and end apply to the image folder the PATH names; its KITTI keys are named as
    dropped (they are not image-folder options)."""
    code = main(["run", str(data / "frames"), "--config", str(kitti_config(tmp_path))])
    err = capsys.readouterr().err
    assert code == 0, err
    run, cfg, metrics = the_run(tmp_path / "runs")
    assert cfg["dataset"]["plugin"] == "images" and cfg["dataset"]["path"] == str(data / "frames")
    assert cfg["dataset"]["resize"] == [128, 96] and cfg["dataset"]["end"] == 16
    assert metrics["timing"]["frames"] == 16
    assert "dataset: from" in err and "resize=[128, 96]" in err
    assert f"dataset: sequence, camera in {tmp_path / 'kitti.toml'} ignored: the images reader has no such option" \
        in err


def merged(path, config, calib=None) -> dict:
    ov, _ = path_overrides(path, calib, config=config)
    return load_config(config, overrides=ov).to_dict()["dataset"]


def test_the_path_sets_the_reader_and_where_the_data_is(layouts, tmp_path, caplog):
    kitti = layouts["kitti"]
    cfg = kitti_config(tmp_path, 'stride = 2\n')
    ds = merged(kitti, cfg)  # the same reader: every key but the location applies
    assert (ds["plugin"], ds["path"], ds["sequence"]) == ("kitti", str(kitti), "my_drive")
    assert ds["camera"] == "image_2" and ds["resize"] == [128, 96] and ds["stride"] == 2 and ds["end"] == 16
    ds = merged(kitti / "image_0", cfg)  # the path names the camera folder: the path's camera
    assert ds["camera"] == "image_0" and ds["resize"] == [128, 96]
    with caplog.at_level(logging.WARNING, logger="pvslam.notice"):
        ds = merged(layouts["euroc"], cfg)  # another reader: its own camera; end and stride apply
    assert (ds["plugin"], ds["camera"], ds["end"], ds["stride"]) == ("euroc", "cam0", 16, 2)
    assert "ignored: the euroc reader has no such option" in caplog.text and "dataset: sequence in" in caplog.text
    # a value another reader's option does not accept is dropped, named; the API takes dicts and objects too
    table = {"dataset": {"plugin": "images", "path": "/x", "timestamps": "filename", "fps": 30.0, "calib": "c.txt"}}
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pvslam.notice"):
        ov, det = path_overrides(layouts["video"], layouts["kitti_calib"], config=table)
    assert ov["dataset"] == {"plugin": "video", "path": str(layouts["video"]), "calib": str(layouts["kitti_calib"]),
                             "fps": 30.0}  # --calib wins over the config's calib
    assert "dataset: timestamps='filename' in the config ignored: not a valid video option" in caplog.text
    assert merged(layouts["tum"], {"dataset": "tum"}) == merged(layouts["tum"], None)
    # time-like file names give timestamps='filename', but a config for the image reader may say otherwise
    assert merged(layouts["tum"] / "rgb", None)["timestamps"] == "filename"
    ds = merged(layouts["tum"] / "rgb", {"dataset": {"plugin": "images", "timestamps": "fps", "fps": 20.0}})
    assert (ds["timestamps"], ds["fps"]) == ("fps", 20.0)


def test_api_run_path_keeps_the_config_dataset_keys(data, tmp_path):
    res = run_path(data / "frames", config=kitti_config(tmp_path))
    saved = json.loads((Path(res.run_dir) / "config.json").read_text())
    assert saved["dataset"]["resize"] == [128, 96] and res.poses.shape == (16, 7)


def test_a_bad_value_for_the_same_reader_is_a_config_error(layouts, tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[dataset]\nplugin = "kitti"\npath = "/nowhere"\nstride = 0\n')
    with pytest.raises(ConfigError, match=r"dataset\.stride"):
        merged(layouts["kitti"], cfg)
    assert main(["run", str(layouts["kitti"]), "--config", str(cfg)]) == 2
