"""`pvslam run PATH [--calib FILE]`: the reader is detected from the path, components that need labels are
switched off on unlabelled data (or a ready learned segmenter is used), sources of unknown length run to their end."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import fakes
from own_data import N, own_data
from pvslam_core.adapt import fit_to_sequence
from pvslam_core.api import run_config, run_path
from pvslam_core.cli import main
from pvslam_core.config import ConfigError, load_config
from pvslam_core.datasets.detect import DetectionError, dataset_section, detect_dataset
from pvslam_core.outputs.trajectory_io import read_tum
from pvslam_core.registry import build_registry, hookimpl
from pvslam_core.types import Intrinsics, SequenceInfo


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return own_data(tmp_path_factory)


def png(path: Path, w: int = 32, h: int = 24) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((h, w, 3), 90, np.uint8))


# ------------------------------------------------------------------------------------------------ detection --
def layouts(root: Path) -> dict[str, Path]:
    """One of each layout the built-in readers detect, written minimally."""
    out = {}
    vid = root / "my clip.MP4"
    vid.write_bytes(b"\x00")  # detection looks at the name only: nothing is decoded
    out["video"] = vid
    for i in range(3):
        png(root / "imgs" / f"img{i}.jpg")
    out["images"] = root / "imgs"
    for i in range(3):
        png(root / "tumnames" / f"{1305031102.175304 + i / 30:.6f}.png")
    out["images_filename"] = root / "tumnames"
    seq = root / "kitti" / "sequences" / "07"
    for cam in ("image_0", "image_2"):
        for i in range(2):
            png(seq / cam / f"{i:06d}.png")
    P = "P{}: 100 0 16 0 0 100 12 0 0 0 1 0\n"
    (seq / "calib.txt").write_text("".join(P.format(k) for k in range(4)))
    (root / "kitti" / "sequences" / "08").mkdir()
    out["kitti_seq"], out["kitti_cam"], out["kitti_root"] = seq, seq / "image_2", root / "kitti"
    cam0 = root / "MH_01" / "mav0" / "cam0"
    png(cam0 / "data" / "1403636579763555584.png")
    (cam0 / "data.csv").write_text("#timestamp [ns],filename\n1403636579763555584,1403636579763555584.png\n")
    (cam0 / "sensor.yaml").write_text("sensor_type: camera\n")
    out["euroc"], out["euroc_mav"] = root / "MH_01", root / "MH_01" / "mav0"
    tum = root / "rgbd_dataset_freiburg1_xyz"
    png(tum / "rgb" / "1.0.png")
    (tum / "rgb.txt").write_text("1.0 rgb/1.0.png\n")
    out["tum"] = tum
    syn = root / "synth"
    for name in ("meta.json", "rgb.txt", "panoptic.json"):
        (syn / name).parent.mkdir(parents=True, exist_ok=True)
        (syn / name).write_text("{}")
    out["synthetic"] = syn
    return out


def test_the_reader_is_detected_from_the_path(tmp_path, monkeypatch):
    L = layouts(tmp_path)
    expect = {
        "video": ("video", {"path": str(L["video"])}),
        "images": ("images", {"path": str(L["images"])}),
        "images_filename": ("images", {"path": str(L["images_filename"]), "timestamps": "filename"}),
        "kitti_seq": ("kitti", {"path": str(L["kitti_root"].resolve()), "sequence": "07", "camera": "image_0"}),
        # an image_2 folder is also a plain image folder: the more specific KITTI match wins
        "kitti_cam": ("kitti", {"path": str(L["kitti_root"].resolve()), "sequence": "07", "camera": "image_2"}),
        "kitti_root": ("kitti", {"path": str(L["kitti_root"].resolve()), "sequence": "07", "camera": "image_0"}),
        "euroc": ("euroc", {"path": str(L["euroc"].resolve()), "camera": "cam0"}),
        "euroc_mav": ("euroc", {"path": str(L["euroc"].resolve()), "camera": "cam0"}),
        "tum": ("tum", {"path": str(L["tum"])}),
        "synthetic": ("synthetic", {"path": str(L["synthetic"])}),  # has TUM's rgb.txt too: more specific
    }
    for key, (plugin, options) in expect.items():
        det = detect_dataset(L[key])
        assert (det.plugin, det.options) == (plugin, options), key
    assert "images" in dict(detect_dataset(L["kitti_cam"]).others)
    monkeypatch.chdir(tmp_path)
    det = detect_dataset("0")  # no file named 0 here: the first camera
    assert (det.plugin, det.options, det.description) == ("video", {"path": "0"}, "camera 0")


def test_paths_nothing_recognises_are_clear_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DetectionError, match=r"empty: no dataset plugin recognises this folder; expected a video file"
                                             r", a folder of images .*\(.*images.*kitti.*video"):
        detect_dataset(tmp_path / "empty")
    with pytest.raises(DetectionError, match=r"notes\.txt: no dataset plugin recognises this file"):
        detect_dataset(tmp_path / "notes.txt")
    with pytest.raises(DetectionError, match=r"nope\.mp4: no such file or folder"):
        detect_dataset(tmp_path / "nope.mp4")
    assert main(["run", str(tmp_path / "nope.mp4")]) == 2


def test_calib_goes_to_the_reader_or_is_refused(tmp_path):
    L = layouts(tmp_path)
    calib = tmp_path / "calib.txt"
    calib.write_text("100 100 15.5 11.5\n")
    assert dataset_section(L["images"], calib).options["calib"] == str(calib)
    det = dataset_section(L["tum"], calib)  # TUM takes a calibration file too (overrides its freiburg preset)
    spec = build_registry().get("dataset", det.plugin)
    k = spec.factory(spec.config_model(**det.options, crop_multiple=1), None).info().intrinsics
    assert (k.fx, k.cx, k.width) == (100, 15.5, 32)
    with pytest.raises(ConfigError, match=r"the euroc reader takes its calibration from the dataset .*no 'calib'"):
        dataset_section(L["euroc"], calib)
    assert dataset_section(L["kitti_seq"], calib).options["calib"] == str(calib)  # KITTI's calib.txt ships apart
    with pytest.raises(ConfigError, match=r"--calib .*missing\.txt: calibration file not found"):
        dataset_section(L["images"], tmp_path / "missing.txt")
    assert main(["run", "--calib", str(calib)]) == 2  # --calib without a PATH


# ------------------------------------------------------------------------------------------ one line: runs --
def test_cli_runs_a_users_video_with_an_orb_slam_calibration(data, tmp_path, capsys):
    out = tmp_path / "runs"
    code = main(["run", str(data / "clip.avi"), "--calib", str(data / "orb.yaml"), "--output-dir", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "pvslam: input: video file clip.avi (video reader)" in err
    assert "pvslam: segmenter: none (the 'labels' segmenter needs panoptic labels, which video_clip does not have)" \
        in err
    (run,) = out.glob("clip-*")  # named after the input
    cfg = json.loads((run / "config.json").read_text())  # records what ran, after fitting it to the data
    assert cfg["dataset"]["plugin"] == "video" and cfg["dataset"]["calib"] == str(data / "orb.yaml")
    assert cfg["segmenter"] == {"plugin": "none"} and cfg["vps"] == {"plugin": "none"}
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["tracking"]["initialized"] and metrics["timing"]["frames"] == N
    assert "panoptic" not in metrics and not list((run / "panoptic").glob("*.png"))
    ts, poses = read_tum(run / "trajectory.txt")
    assert len(ts) == N and np.ptp(poses[:, :3], axis=0).max() > 0  # real motion, not placeholders
    assert "segmenter: none" in (run / "log.txt").read_text()
    _advice_is_what_the_plugin_and_the_catalogue_have(err)


def _advice_is_what_the_plugin_and_the_catalogue_have(err: str) -> None:
    """The notice spells out a catalogue name and a preset of ``panoptic_fpn`` (the core cannot import the plugin):
    they must be the catalogue entry that preset loads by default."""
    import re

    from pvslam_core import weights as W
    from pvslam_plugins.segmenters.panoptic_fpn.segmenter import DEFAULT_WEIGHTS

    name = re.search(r"pvslam weights fetch ([\w.-]+)`", err).group(1)
    preset = re.search(r'segmenter\.preset = "(\w+)"', err).group(1)
    assert DEFAULT_WEIGHTS[preset] == name
    assert W.find(name, W.catalog_weights()) is not None


def test_api_run_path_on_an_image_folder_with_overrides(data, tmp_path):
    res = run_path(data / "frames", overrides=[f"run.output_dir={json.dumps(str(tmp_path))}", "run.progress=false",
                                               "dataset.stride=2", "run.name=mine"])
    assert res.poses.shape == (N // 2, 7) and Path(res.run_dir).name.startswith("mine-")
    cfg = json.loads((Path(res.run_dir) / "config.json").read_text())
    assert cfg["dataset"]["plugin"] == "images" and cfg["dataset"]["stride"] == 2  # calib.txt found in the folder


def test_a_config_file_keeps_everything_but_its_dataset(data, tmp_path):
    cfg = tmp_path / "kitti.toml"
    cfg.write_text('[dataset]\nplugin = "kitti"\npath = "/nowhere"\nsequence = "06"\n[graph.init]\nwarmup = 4\n'
                   f'[run]\noutput_dir = {json.dumps(str(tmp_path / "runs"))}\nprogress = false\nmax_frames = 12\n')
    res = run_path(data / "frames", config=cfg)
    saved = json.loads((Path(res.run_dir) / "config.json").read_text())
    assert saved["dataset"]["plugin"] == "images" and "sequence" not in saved["dataset"]
    assert saved["graph"]["init"]["warmup"] == 4 and res.poses.shape == (12, 7)


# ---------------------------------------------------------------------------------- fitting to the data --
class _Segmenters:
    """Test plugins: an oracle that needs labels, a learned segmenter whose readiness the test sets."""

    ready = True

    @hookimpl
    def register_segmenters(self, register):
        from pvslam_core.config_base import PluginConfig

        class Cfg(PluginConfig):
            pass

        register("oracle", lambda c, ctx: None, Cfg, needs_gt_panoptic=True)
        register("learned", lambda c, ctx: None, Cfg, auto_ready=lambda: _Segmenters.ready)
        register("broken", lambda c, ctx: None, Cfg, auto_ready=lambda: 1 / 0)


def test_fit_to_sequence(monkeypatch):
    reg = build_registry(extra_modules=(fakes, _Segmenters()))
    k = Intrinsics(200, 200, 159.5, 119.5, 320, 240)  # large enough to keep the default BA resolution
    plain, labelled = SequenceInfo("mine", 10, k), SequenceInfo("syn", 10, k, has_gt_panoptic=True)
    cfg = load_config(overrides=["segmenter.plugin=oracle", "vps.plugin=pass", "dataset.plugin=fake"], registry=reg)
    assert fit_to_sequence(cfg, labelled, reg) == (cfg, [])  # labels present: unchanged
    fitted, notes = fit_to_sequence(cfg, plain, reg)
    assert fitted.pipeline.segmenter.plugin == "learned" and fitted.pipeline.vps.plugin == "pass"
    assert notes == ["segmenter: learned (the 'oracle' segmenter needs panoptic labels, which mine does not have; "
                     "learned is installed and ready)"]
    assert cfg.pipeline.segmenter.plugin == "oracle"  # the input is not modified
    monkeypatch.setattr(_Segmenters, "ready", False)
    fitted, notes = fit_to_sequence(cfg, plain, reg)
    assert fitted.pipeline.segmenter.plugin == "none" and fitted.pipeline.vps.plugin == "none"
    assert fitted.models["segmenter"] is None and "panoptic evaluation are off" in notes[0]
    chosen = load_config(overrides=["segmenter.plugin=learned", "dataset.plugin=fake"], registry=reg)
    assert fit_to_sequence(chosen, plain, reg) == (chosen, [])  # a segmenter that needs no labels is kept


class _Endless(fakes.FakeDataset):
    """The fake scene as a live source: no frame count."""

    def info(self):
        info = super().info()
        info.num_frames = None
        return info


class _LivePlugin:
    @hookimpl
    def register_datasets(self, register):
        register("live", lambda c, ctx: _Endless(c), fakes.FakeDatasetConfig)


@pytest.mark.parametrize("max_frames, expected", [(None, 12), (7, 7)])
def test_a_source_of_unknown_length_runs_to_its_end(fake_config_file, max_frames, expected):
    reg = build_registry(extra_modules=(fakes, _LivePlugin()))
    ov = ["dataset.plugin=live"] + ([f"run.max_frames={max_frames}"] if max_frames else [])
    res = run_config(fake_config_file, overrides=ov, registry=reg)
    assert res.poses.shape == (expected, 7)
    said = "unknown number of frames" if max_frames is None else f"{max_frames} frames"
    assert f"sequence fake: {said}" in (Path(res.run_dir) / "log.txt").read_text()


def test_a_video_that_claims_too_few_frames_is_read_to_its_end(data, tmp_path, monkeypatch, caplog):
    """The container's frame count is the progress bar's total, not where the run stops."""
    real = cv2.VideoCapture

    class Claims10:
        def __init__(self, *a):
            self.cap = real(*a)

        def get(self, prop):
            return 10.0 if prop == cv2.CAP_PROP_FRAME_COUNT else self.cap.get(prop)

        def __getattr__(self, name):
            return getattr(self.cap, name)

    monkeypatch.setattr(cv2, "VideoCapture", Claims10)
    with caplog.at_level("INFO"):
        res = run_path(data / "clip.avi", calib=data / "orb.yaml",
                       overrides=[f"run.output_dir={json.dumps(str(tmp_path))}", "run.progress=false"])
    assert res.poses.shape == (N, 7)
    assert "sequence video_clip: 10 frames" in caplog.text  # the claim: the progress bar's total
    assert f"the container claims 10 frames, {N} were decoded" in caplog.text


def test_ba_resolution_follows_the_focal_length(monkeypatch):
    """graph.ba_downsample is halved while the focal length at BA resolution would be below adapt.BA_MIN_FOCAL (24
    BA px per radian) unless the user set it, the rule is off (0), or the frontend registered a fixed one
    (raft_gru: its feature stride).  A wide image of few rows keeps 1/8: KITTI at half size was halved by the
    earlier row-count rule, which quadrupled its BA grid and cut its speed 3x."""
    reg = build_registry(extra_modules=(fakes,))

    def fitted(w, h, *ov, f=None):
        f = float(w if f is None else f)
        cfg = load_config(overrides=["dataset.plugin=fake", *ov], registry=reg)
        info = SequenceInfo("cam", 10, Intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h), has_gt_panoptic=True)
        before = cfg.pipeline.graph.ba_downsample
        out, notes = fit_to_sequence(cfg, info, reg)
        assert cfg.pipeline.graph.ba_downsample == before  # the input is not modified
        return out.pipeline.graph.ba_downsample, notes

    assert fitted(320, 240, f=272) == (8, [])  # the synthetic camera everything was tuned on: 34 BA px
    assert fitted(616, 184, f=353.5) == (8, [])  # KITTI 06 at half size (configs/kitti.toml): 44 BA px, 23 rows
    assert fitted(1241, 376, f=718.9) == (8, [])
    ds, notes = fitted(160, 120, f=136)  # 17 BA px at 1/8 -> 34 at 1/4
    assert ds == 4 and len(notes) == 1 and "17.0 BA px" in notes[0] and "graph.ba_downsample" in notes[0]
    assert fitted(640, 480, f=160)[0] == 4  # a wide-angle lens: 20 BA px at 1/8, though the grid has 60 rows
    assert fitted(64, 48)[0] == 2 and fitted(64, 48, f=40)[0] == 1  # 8 -> 16 -> 32; 5 -> 10 -> 20 -> 40
    assert fitted(160, 120, "graph.ba_downsample=8", f=136) == (8, [])  # the user's choice stands
    assert fitted(160, 120, "graph.ba_downsample=6", f=136)[0] == 6  # set explicitly: never touched
    assert fitted(160, 120, "frontend.plugin=raft_gru", f=136) == (8, [])  # a network's fixed stride
    import pvslam_core.adapt as adapt

    monkeypatch.setattr(adapt, "BA_MIN_FOCAL", 0.0)
    assert fitted(160, 120, f=136) == (8, [])  # the rule off


def test_the_pipeline_builds_its_frontend_at_the_fitted_resolution(tmp_path):
    """Without graph.ba_downsample the fake 64x48 scene (focal length 40 px) runs at 1/1: the frontend is built with
    the fitted factor (its targets would not match the graph's grid otherwise), config.json records it, the log
    says why."""
    import json

    p = tmp_path / "pipeline.toml"
    text = fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix())
    p.write_text(text.replace("ba_downsample = 4\n", ""))
    res = run_config(p, registry=build_registry(extra_modules=(fakes,)))
    assert res.poses.shape == (12, 7) and bool(res.poses.isfinite().all())
    run = Path(res.run_dir)
    assert json.loads((run / "config.json").read_text())["graph"]["ba_downsample"] == 1
    log = (run / "log.txt").read_text()
    assert "graph.ba_downsample: 1 (at 1/8 the 64x48 camera's focal length 40 px is 5.0 BA px" in log


def test_old_ba_min_rows_key_still_loads_with_a_warning(caplog):
    """config.json of run directories written before the focal rule carry graph.ba_min_rows: they load (the key is
    ignored, the focal rule applies) and the log says so."""
    with caplog.at_level("WARNING", logger="pvslam.config"):
        cfg = load_config({"graph": {"ba_min_rows": 30}})
    assert "ba_min_rows" in caplog.text and "ignored" in caplog.text
    import pvslam_core.adapt as adapt

    assert cfg.pipeline.graph.ba_downsample == 8 and adapt.BA_MIN_FOCAL == 24.0
    with pytest.raises(ConfigError, match="ba_min_row"):  # a typo of it is still an error
        load_config({"graph": {"ba_min_row": 30}})
