"""The ``kitti`` reader: on the shared KITTI excerpts (when present) and on layouts written by the test; a
sequence folder is recognised by its content wherever it is (symlinks included), times.txt may have more rows
than images, and the real excerpts run in one line (`pvslam run PATH --calib calib.txt`)."""
from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pvslam_core.cli import main
from pvslam_core.datasets.base import DatasetError
from pvslam_core.datasets.detect import dataset_section, detect_dataset
from pvslam_core.outputs.trajectory_io import pose_to_matrix
from pvslam_plugins.datasets.kitti.config import KittiConfig
from pvslam_plugins.datasets.kitti.reader import KittiReader

@pytest.fixture(scope="module")
def KITTI(shared_dir) -> Path:
    """The shared KITTI odometry excerpts (a missing shared folder fails the test, see the root conftest)."""
    return shared_dir / "data" / "kitti-odometry"


# ------------------------------------------------------------------------------------------- real excerpts ----
def test_sequence_06_excerpt(KITTI):
    r = KittiReader(KittiConfig(path=str(KITTI), sequence="06", max_pixels=None))  # the native size
    info = r.info()
    assert info.num_frames == 51 and info.has_gt_pose
    k = info.intrinsics  # P0 of sequence 06, 1226x370 centre-cropped to 1224x368
    assert (k.width, k.height) == (1224, 368)
    assert k.fx == pytest.approx(707.0912) and k.fy == pytest.approx(707.0912)
    assert k.cx == pytest.approx(601.8873 - 1) and k.cy == pytest.approx(183.1104 - 1)
    f0, f3 = r[0], r[3]
    assert tuple(f0.image.shape) == (3, 368, 1224)
    assert torch.equal(f0.image[0], f0.image[1]) and torch.equal(f0.image[0], f0.image[2])
    raw = cv2.imread(str(KITTI / "sequences/06/image_0/000003.png"), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(f3.image[0].numpy(), raw[1:369, 1:1225])
    times = np.loadtxt(KITTI / "sequences/06/times.txt")
    assert f3.timestamp == pytest.approx(times[3])
    gt = np.loadtxt(KITTI / "poses/06.txt").reshape(-1, 3, 4)
    assert np.allclose(pose_to_matrix(f3.gt_pose.numpy())[:3], gt[3], atol=1e-6)


def test_sequence_01_without_times_falls_back_to_10hz(caplog, KITTI):
    with caplog.at_level(logging.WARNING):
        r = KittiReader(KittiConfig(path=str(KITTI), sequence="01", stride=5, resize=(620, 188)))
    assert "no times.txt" in caplog.text and "10 Hz" in caplog.text
    frames = list(r)
    assert len(frames) == 11 and [f.index for f in frames] == list(range(11))
    assert [f.timestamp for f in frames] == pytest.approx([0.5 * i for i in range(11)])
    k = r.info().intrinsics
    assert (k.width, k.height) == (616, 184) and frames[0].width == 616
    assert k.fx == pytest.approx(718.856 * 620 / 1241)


def test_missing_camera_folder(KITTI):
    with pytest.raises(DatasetError, match="image_2"):
        KittiReader(KittiConfig(path=str(KITTI), sequence="06", camera="image_2"))


# ---------------------------------------------------------------------------------------- written layouts ----
K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
T2 = np.array([0.06, -0.001, 0.002])  # camera 2 = camera 0 + T2 (X_2 = X_0 + T2)


def fake_kitti(root: Path, n: int = 4, times: bool = True) -> np.ndarray:
    seq = root / "sequences" / "07"
    for cam in ("image_0", "image_2"):
        (seq / cam).mkdir(parents=True)
        for i in range(n):
            img = np.full((48, 64, 3) if cam == "image_2" else (48, 64), 20 * i, np.uint8)
            cv2.imwrite(str(seq / cam / f"{i:06d}.png"), img)
    P0 = np.hstack([K, np.zeros((3, 1))])
    P2 = np.hstack([K, (K @ T2)[:, None]])
    lines = [f"P{j}: " + " ".join(f"{v:.12e}" for v in P.reshape(-1)) for j, P in enumerate([P0, P0, P2, P2])]
    (seq / "calib.txt").write_text("\n".join(lines) + "\n")
    if times:
        (seq / "times.txt").write_text("".join(f"{0.1037 * i:.6e}\n" for i in range(n)))
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        a = rng.normal(size=3) * 0.3
        T[i, :3, :3] = cv2.Rodrigues(a)[0]
        T[i, :3, 3] = rng.normal(size=3) * 5
    (root / "poses").mkdir()
    (root / "poses" / "07.txt").write_text("".join(" ".join(f"{v:.12e}" for v in t[:3].reshape(-1)) + "\n" for t in T))
    return T


def test_image_2_pose_is_offset_by_the_camera_baseline(tmp_path):
    T = fake_kitti(tmp_path)
    r0 = KittiReader(KittiConfig(path=str(tmp_path), sequence="07", crop_multiple=1))
    r2 = KittiReader(KittiConfig(path=str(tmp_path), sequence="07", camera="image_2", crop_multiple=1))
    for i in range(4):
        f0, f2 = r0[i], r2[i]
        T_wc0, T_wc2 = pose_to_matrix(f0.gt_pose.numpy()), pose_to_matrix(f2.gt_pose.numpy())
        assert np.allclose(T_wc0, T[i], atol=1e-9)
        # same orientation; camera-2 centre is -T2 in camera 0 (0.06 m along -x for KITTI's +0.06)
        assert np.allclose(T_wc2[:3, :3], T[i, :3, :3], atol=1e-9)
        assert np.allclose(T_wc2[:3, 3], T[i, :3, 3] - T[i, :3, :3] @ T2, atol=1e-9)
        # a world point seen by camera 0 at X0 is seen by camera 2 at X0 + T2
        Xw = np.array([1.0, -2.0, 7.0, 1.0])
        X0 = np.linalg.inv(T_wc0) @ Xw
        X2 = np.linalg.inv(T_wc2) @ Xw
        assert np.allclose(X2[:3], X0[:3] + T2, atol=1e-9)
    assert r2[1].image[:, 0, 0].tolist() == [20, 20, 20]
    assert r2[0].timestamp == 0 and r2[2].timestamp == pytest.approx(0.2074)


def test_missing_frame_names_the_file(tmp_path):
    fake_kitti(tmp_path)
    (tmp_path / "sequences/07/image_0/000002.png").unlink()
    with pytest.raises(DatasetError, match=r"000002\.png: frame missing.*times\.txt"):
        KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))


def test_gap_without_times_is_a_missing_frame(tmp_path):
    fake_kitti(tmp_path, times=False)
    (tmp_path / "sequences/07/image_0/000001.png").unlink()
    with pytest.raises(DatasetError, match=r"000001\.png: frame missing"):
        KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))


def test_corrupt_image_names_the_file(tmp_path):
    fake_kitti(tmp_path)
    (tmp_path / "sequences/07/image_0/000001.png").write_bytes(b"not a png")
    r = KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))
    with pytest.raises(DatasetError, match=r"000001\.png: unreadable or corrupt"):
        r[1]


def test_calibration_with_wrong_count_names_file_and_count(tmp_path):
    fake_kitti(tmp_path)
    calib = tmp_path / "sequences/07/calib.txt"
    lines = calib.read_text().splitlines()
    lines[0] = lines[0].rsplit(" ", 1)[0]
    calib.write_text("\n".join(lines))
    with pytest.raises(DatasetError, match=r"calib\.txt:1: P0 needs 12 values.*found 11"):
        KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))


def test_unsorted_times_names_the_file(tmp_path):
    fake_kitti(tmp_path)
    (tmp_path / "sequences/07/times.txt").write_text("0\n0.2\n0.1\n0.3\n")
    with pytest.raises(DatasetError, match=r"times\.txt: unsorted"):
        KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))


def test_too_few_poses_names_the_file(tmp_path):
    fake_kitti(tmp_path)
    p = tmp_path / "poses/07.txt"
    p.write_text("".join(p.read_text().splitlines(keepends=True)[:2]))
    with pytest.raises(DatasetError, match=r"07\.txt: 2 poses for 4 frames"):
        KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))


def test_end_out_of_range(tmp_path):
    fake_kitti(tmp_path)
    r = KittiReader(KittiConfig(path=str(tmp_path), sequence="07", end=5))
    with pytest.raises(DatasetError, match=r"sequences/07: end=5 is out of range.*4 frames"):
        r.info()


def test_missing_sequence(tmp_path):
    with pytest.raises(DatasetError, match="sequence folder not found"):
        KittiReader(KittiConfig(path=str(tmp_path), sequence="99"))


def test_registered_through_the_hook(monkeypatch):
    import pvslam_plugins.datasets.kitti as plugin
    from pvslam_core.registry import build_registry

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    assert build_registry(extra_modules=(plugin,)).get("dataset", "kitti").config_model is KittiConfig



def test_invalid_projection_matrix_names_the_calibration_file(tmp_path):
    fake_kitti(tmp_path)
    calib = tmp_path / "sequences/07/calib.txt"
    lines = calib.read_text().splitlines()
    vals = lines[0].split()
    vals[1] = "0.0"  # P0: fx = 0
    lines[0] = " ".join(vals)
    calib.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as err:
        KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))
    msg = str(err.value)
    assert str(calib) in msg and "P0" in msg and "fx=0.0" in msg


# ------------------------------------------------------------------------- sequence folders anywhere ----
def reader(det) -> KittiReader:
    assert det.plugin == "kitti", det
    return KittiReader(KittiConfig(**det.options, crop_multiple=1))


def test_a_sequence_folder_is_recognised_by_its_content_wherever_it_is(tmp_path):
    fake_kitti(tmp_path / "kitti")
    mine = tmp_path / "my drives" / "drive_a"
    shutil.copytree(tmp_path / "kitti" / "sequences" / "07", mine)
    det = detect_dataset(mine)
    assert det.options == {"path": str(mine), "sequence": "drive_a", "camera": "image_0"}
    r = reader(det)
    info = r.info()
    assert info.num_frames == 4 and info.name == "kitti_drive_a_image_0" and not info.has_gt_pose
    assert (info.intrinsics.fx, info.intrinsics.cx) == (K[0, 0], K[0, 2])
    assert r[2].timestamp == pytest.approx(0.2074)
    det = detect_dataset(mine / "image_2")
    assert det.options["camera"] == "image_2" and reader(det)[0].image.shape[1:] == (48, 64)


def test_a_symlinked_sequences_folder_and_a_symlinked_sequence(tmp_path):
    """`sequences` is a link to a folder of another name (its ground truth is found through the link), and a
    link named anything points at one sequence."""
    fake_kitti(tmp_path / "store")
    os.rename(tmp_path / "store" / "sequences", tmp_path / "store" / "odometry_seqs")
    root = tmp_path / "kitti"
    root.mkdir()
    (root / "sequences").symlink_to(tmp_path / "store" / "odometry_seqs")
    (root / "poses").symlink_to(tmp_path / "store" / "poses")
    det = detect_dataset(root / "sequences" / "07")
    assert det.options == {"path": str(root), "sequence": "07", "camera": "image_0"}
    assert reader(det).info().has_gt_pose
    link = tmp_path / "latest"
    link.symlink_to(root / "sequences" / "07")
    det = detect_dataset(link)
    assert det.options == {"path": str(link), "sequence": "latest", "camera": "image_0"}
    assert len(reader(det)) == 4


def test_times_txt_with_more_rows_than_images_uses_the_first(tmp_path, caplog):
    fake_kitti(tmp_path)
    times = tmp_path / "sequences" / "07" / "times.txt"
    times.write_text("".join(f"{0.1 * i:.6e}\n" for i in range(6)))
    with caplog.at_level(logging.WARNING):
        r = KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))
    assert len(r) == 4 and r[3].timestamp == pytest.approx(0.3) and r.info().has_gt_pose
    assert f"{times}: 6 timestamps for 4 images" in caplog.text and "using the first 4" in caplog.text
    times.write_text("0\n0.1\n0.2\n")
    with pytest.raises(DatasetError, match=r"times\.txt: 3 timestamps for 4 images in .*image_0"):
        KittiReader(KittiConfig(path=str(tmp_path), sequence="07"))


def test_a_sequence_without_calib_txt_takes_calib(tmp_path):
    """KITTI ships calib.txt in a separate archive: a sequence folder with times.txt is recognised without it, and
    `--calib` gives it (the kitti reader's `calib`)."""
    fake_kitti(tmp_path)
    seq = tmp_path / "sequences" / "07"
    (seq / "calib.txt").rename(tmp_path / "calib.txt")
    det = detect_dataset(seq)
    with pytest.raises(DatasetError, match=r"calib\.txt: calibration file not found \(KITTI ships it in "
                                           r"data_odometry_calib; or give --calib FILE\)"):
        reader(det)
    det = dataset_section(seq, tmp_path / "calib.txt")
    assert det.options["calib"] == str(tmp_path / "calib.txt") and reader(det).info().intrinsics.fx == K[0, 0]


# ------------------------------------------------------------------------------------------- real excerpts ----
SHORT = '[dataset]\nresize = [620, 188]\nend = 24\n[loop]\nplugin = "none"\n'


@pytest.fixture(scope="module")
def seq00(shared_dir) -> Path:
    seq = shared_dir / "data" / "kitti-odometry" / "sequences" / "00"
    if not (seq / "calib.txt").is_file():
        pytest.skip(f"{seq}: KITTI excerpt not present")
    return seq


def run_cli(path: Path, calib: Path, tmp_path: Path, capsys) -> tuple[dict, dict, str]:
    cfg = tmp_path / "short.toml"
    cfg.write_text(SHORT)
    out = tmp_path / "runs"
    code = main(["run", str(path), "--calib", str(calib), "--config", str(cfg), "--output-dir", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 0, err
    (run,) = out.iterdir()
    return (json.loads((run / "config.json").read_text()), json.loads((run / "metrics.json").read_text()),
            err + (run / "log.txt").read_text())


def test_real_excerpt_runs_in_one_line_with_its_calib_txt(seq00, tmp_path, capsys):
    cfg, metrics, said = run_cli(seq00, seq00 / "calib.txt", tmp_path, capsys)
    assert "pvslam: input: KITTI odometry sequence 00 (image_0)" in said
    assert cfg["dataset"]["plugin"] == "kitti" and cfg["dataset"]["sequence"] == "00"
    assert cfg["dataset"]["resize"] == [620, 188] and metrics["timing"]["frames"] == 24  # the config's keys apply
    assert metrics["tracking"]["initialized"]
    assert "ate" in metrics  # poses/00.txt found beside sequences/


def test_real_excerpt_under_a_parent_not_named_sequences(seq00, tmp_path, capsys):
    """The excerpt's images linked into a folder of another name, calib.txt copied, a full-length times.txt (more
    rows than the excerpt's images)."""
    mine = tmp_path / "drives" / "city"
    mine.mkdir(parents=True)
    (mine / "image_0").symlink_to(seq00 / "image_0")
    shutil.copy(seq00 / "calib.txt", mine / "calib.txt")
    n = len(list((seq00 / "image_0").glob("*.png")))
    (mine / "times.txt").write_text("".join(f"{i / 10:.6e}\n" for i in range(4541)))
    cfg, metrics, said = run_cli(mine, mine / "calib.txt", tmp_path, capsys)
    assert "pvslam: input: KITTI odometry sequence city (image_0)" in said
    assert f"4541 timestamps for {n} images" in said
    assert cfg["dataset"]["path"] == str(mine) and metrics["timing"]["frames"] == 24
    assert metrics["tracking"]["initialized"]
