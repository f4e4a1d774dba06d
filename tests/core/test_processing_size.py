"""The processing size every reader chooses from the input (``max_pixels`` of the shared reader options).

Each reader kind reads small files written here; the geometry is checked the way it is used: a bright blob drawn at
an input pixel must be found, in the yielded frame, where the reported intrinsics put the same ray.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from pvslam_core.datasets.base import MAX_PIXELS, ReaderOptions, processing_size
from pvslam_core.types import Intrinsics

W, H = 128, 96  # the input written by the tests
K = Intrinsics(100.0, 100.0, 63.5, 47.5, W, H)
AREA = 4096  # max_pixels of the tests: 73x55 after the resize, 72x48 after the crop to multiples of 8
BLOB = (90.0, 30.0)  # input pixel of the blob


def blob_image(w: int = W, h: int = H, at=BLOB) -> np.ndarray:
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    img = 255.0 * np.exp(-((xs - at[0]) ** 2 + (ys - at[1]) ** 2) / (2 * 3.0**2))
    return np.clip(img, 0, 255).astype(np.uint8)


def centroid(gray: np.ndarray) -> np.ndarray:
    g = np.clip(gray.astype(np.float64) - 0.2 * gray.max(), 0, None)
    ys, xs = np.mgrid[0 : g.shape[0], 0 : g.shape[1]]
    return np.array([(g * xs).sum() / g.sum(), (g * ys).sum() / g.sum()])


def calib_line(k: Intrinsics = K) -> str:
    return f"{k.fx} {k.fy} {k.cx} {k.cy}\n"


# ------------------------------------------------------------------------------------ one fake per kind --
def images_reader(root: Path, **opts):
    from pvslam_plugins.datasets.images.config import ImagesConfig
    from pvslam_plugins.datasets.images.reader import ImagesReader

    d = root / "frames"
    d.mkdir()
    for i in range(3):
        cv2.imwrite(str(d / f"{i:04d}.png"), blob_image())
    (d / "calib.txt").write_text(calib_line())
    return ImagesReader(ImagesConfig(path=str(d), **opts))


def kitti_reader(root: Path, **opts):
    from pvslam_plugins.datasets.kitti.config import KittiConfig
    from pvslam_plugins.datasets.kitti.reader import KittiReader

    seq = root / "sequences" / "07"
    (seq / "image_0").mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), blob_image())
    P = np.hstack([K.matrix().numpy().astype(np.float64), np.zeros((3, 1))])
    (seq / "calib.txt").write_text("".join(f"P{j}: " + " ".join(f"{v:.12e}" for v in P.reshape(-1)) + "\n"
                                           for j in range(4)))
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(3)))
    return KittiReader(KittiConfig(path=str(root), sequence="07", **opts))


def euroc_reader(root: Path, **opts):
    from pvslam_plugins.datasets.euroc.config import EurocConfig
    from pvslam_plugins.datasets.euroc.reader import EurocReader

    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    stamps = [1403636579763555584 + i * 50_000_000 for i in range(3)]
    for t in stamps:
        cv2.imwrite(str(cam / "data" / f"{t}.png"), blob_image())
    (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in stamps))
    (cam / "sensor.yaml").write_text(
        "sensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, "
        f"1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\nrate_hz: 20\nresolution: [{W}, {H}]\ncamera_model: pinhole\n"
        f"intrinsics: [{K.fx}, {K.fy}, {K.cx}, {K.cy}]\ndistortion_model: radial-tangential\n"
        "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n")
    return EurocReader(EurocConfig(path=str(root), **opts))


def tum_reader(root: Path, **opts):
    from pvslam_plugins.datasets.tum.config import TumConfig
    from pvslam_plugins.datasets.tum.reader import TumReader

    seq = root / "my_room"
    (seq / "rgb").mkdir(parents=True)
    lines = []
    for i in range(3):
        t = 1305031102.0 + 0.033 * i
        cv2.imwrite(str(seq / f"rgb/{t:.6f}.png"), blob_image())
        lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (seq / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(lines) + "\n")
    (seq / "calib.txt").write_text(calib_line())
    return TumReader(TumConfig(path=str(seq), **opts))


def video_reader(root: Path, **opts):
    from pvslam_plugins.datasets.video.config import VideoConfig
    from pvslam_plugins.datasets.video.reader import VideoReader

    path = root / "clip.avi"
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert wr.isOpened(), "opencv cannot write MJPG/AVI here"
    for _ in range(3):
        wr.write(cv2.cvtColor(blob_image(), cv2.COLOR_GRAY2BGR))
    wr.release()
    return VideoReader(VideoConfig(path=str(path), calib=[K.fx, K.fy, K.cx, K.cy], **opts))


KINDS = {"images": images_reader, "kitti": kitti_reader, "euroc": euroc_reader, "tum": tum_reader,
         "video": video_reader}


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_every_reader_shrinks_to_max_pixels_with_intrinsics_that_follow(kind, tmp_path):
    reader = KINDS[kind](tmp_path, max_pixels=AREA)
    info = reader.info()
    k = info.intrinsics
    assert (k.width, k.height) == (72, 48)  # 73x55 (area <= 4096, aspect kept), centre-cropped to multiples of 8
    assert k.width * k.height <= AREA and k.width % 8 == 0 and k.height % 8 == 0
    assert (info.input_intrinsics.width, info.input_intrinsics.height) == (W, H)
    assert k.fx / K.fx == pytest.approx(k.fy / K.fy, rel=0.02)  # one scale for both axes: the aspect is kept
    frame = next(iter(reader))
    assert tuple(frame.image.shape) == (3, 48, 72) and frame.intrinsics == k
    # the blob's ray lands where the reported intrinsics project it
    ray = ((BLOB[0] - K.cx) / K.fx, (BLOB[1] - K.cy) / K.fy)
    expected = np.array([k.fx * ray[0] + k.cx, k.fy * ray[1] + k.cy])
    np.testing.assert_allclose(centroid(frame.image[0].numpy()), expected, atol=0.35)


def test_the_default_shrinks_a_kitti_size_input(tmp_path):
    """The default area takes KITTI's 1241x376 frames to 805x244 (DROID-SLAM's area), cropped to 800x240."""
    assert processing_size(1241, 376, ReaderOptions()) == (805, 244)
    d = tmp_path / "big"
    d.mkdir()
    cv2.imwrite(str(d / "0.png"), blob_image(1241, 376, at=(900.0, 100.0)))
    from pvslam_plugins.datasets.images.config import ImagesConfig
    from pvslam_plugins.datasets.images.reader import ImagesReader

    reader = ImagesReader(ImagesConfig(path=str(d), calib=[718.856, 718.856, 607.1928, 185.2157]))
    k = reader.info().intrinsics
    assert (k.width, k.height) == (800, 240)
    assert k.fx == pytest.approx(718.856 * 805 / 1241) and k.fy == pytest.approx(718.856 * 244 / 376)
    # the blob's ray lands where the intrinsics put it
    ray = ((900.0 - 607.1928) / 718.856, (100.0 - 185.2157) / 718.856)
    expected = np.array([k.fx * ray[0] + k.cx, k.fy * ray[1] + k.cy])
    np.testing.assert_allclose(centroid(reader[0].image[0].numpy()), expected, atol=0.35)


@pytest.mark.parametrize("size", [(320, 240), (200, 100), (64, 48)])
def test_never_enlarges(size):
    w, h = size
    assert processing_size(w, h, ReaderOptions()) == (w, h)  # under the default area
    assert processing_size(w, h, ReaderOptions(max_pixels=10 ** 7)) == (w, h)
    assert processing_size(w, h, ReaderOptions(max_pixels=max(4096, w * h))) == (w, h)


def test_the_default_synthetic_size_is_not_resized(tmp_path):
    """The 320x240 default camera is under the default area: the frames pass untouched (no message either)."""
    reader = images_reader_sized(tmp_path, 320, 240)
    info = reader.info()
    assert (info.intrinsics.width, info.intrinsics.height) == (320, 240) and info.input_intrinsics is None


def images_reader_sized(root: Path, w: int, h: int, **opts):
    from pvslam_plugins.datasets.images.config import ImagesConfig
    from pvslam_plugins.datasets.images.reader import ImagesReader

    d = root / f"f{w}x{h}"
    d.mkdir()
    cv2.imwrite(str(d / "0.png"), blob_image(w, h, at=(w * 0.7, h * 0.3)))
    return ImagesReader(ImagesConfig(path=str(d), calib=[0.85 * w, 0.85 * w, (w - 1) / 2, (h - 1) / 2], **opts))


def test_an_explicit_resize_wins_over_max_pixels(tmp_path):
    reader = images_reader_sized(tmp_path, 640, 480, resize=(400, 200), max_pixels=4096)
    k = reader.info().intrinsics
    assert (k.width, k.height) == (400, 200)
    reader = images_reader_sized(tmp_path, 64, 48, resize=(128, 96))  # resize may enlarge; max_pixels never does
    assert (reader.info().intrinsics.width, reader.info().intrinsics.height) == (128, 96)


def test_null_max_pixels_keeps_the_native_size(tmp_path):
    reader = images_reader_sized(tmp_path, 640, 480, max_pixels=None)
    info = reader.info()
    assert (info.intrinsics.width, info.intrinsics.height) == (640, 480) and info.input_intrinsics is None


@pytest.mark.parametrize("bad", [0, -5, 100])
def test_a_nonsense_max_pixels_is_refused_with_its_value(bad):
    with pytest.raises(ValidationError, match="max_pixels must be at least 4096") as e:
        ReaderOptions(max_pixels=bad)
    assert f"input_value={bad}" in str(e.value)  # pydantic names the value given


def test_a_nonsense_max_pixels_is_one_error_line_on_the_command_line(tmp_path, capsys):
    from pvslam_core.cli import main

    reader_dir = tmp_path / "frames"
    reader_dir.mkdir()
    cv2.imwrite(str(reader_dir / "0.png"), blob_image())
    code = main(["run", str(reader_dir), "--calib", str(_calib_file(tmp_path)), "--set", "dataset.max_pixels=-1",
                 "--output-dir", str(tmp_path / "runs"), "-q"])
    err = capsys.readouterr().err
    assert code != 0 and "Traceback" not in err
    line = [s for s in err.splitlines() if s.startswith("pvslam: error:")]
    assert len(line) == 1 and "max_pixels" in line[0] and "-1" in line[0]


def _calib_file(root: Path) -> Path:
    p = root / "calib.txt"
    p.write_text(calib_line())
    return p


def test_the_area_keeps_the_aspect_within_a_pixel():
    for w, h in [(1241, 376), (1920, 1080), (752, 480), (640, 480), (4000, 3000)]:
        sw, sh = processing_size(w, h, ReaderOptions(max_pixels=MAX_PIXELS))
        assert sw * sh <= MAX_PIXELS and abs(sw / w - sh / h) <= 1.0 / min(sw, sh)
        assert sw * sh >= MAX_PIXELS * (1 - 2 / min(sw, sh))  # as large as the area allows
        assert math.isclose(sw / sh, w / h, rel_tol=2 / min(sw, sh))


def test_the_streaming_tracker_chooses_the_size_too():
    from pvslam_core.api import Tracker

    with Tracker(intrinsics=[K.fx, K.fy, K.cx, K.cy], max_pixels=AREA) as tracker:
        tracker.track(np.repeat(blob_image()[..., None], 3, axis=2), 0.0)
        out, info = tracker.geometry.out, tracker.pipeline.info
        assert (out.width, out.height) == (72, 48)
        assert (info.input_intrinsics.width, info.input_intrinsics.height) == (W, H)


@pytest.mark.parametrize("gray", [True, False])
def test_a_resized_frame_is_the_same_per_plane_whether_the_source_is_gray_or_colour(gray):
    """A gray source (KITTI, EuRoC: three equal planes) is resized once and replicated; the pixels must be those of
    resizing every plane, and a colour frame must keep its own planes."""
    from pvslam_core.datasets.base import _apply, _apply_planes

    class Geo:
        undist_maps, resize, crop = None, (61, 45), (2, 1, 56, 40)

    rng = np.random.default_rng(0)
    plane = cv2.GaussianBlur(rng.integers(0, 256, (H, W), dtype=np.uint8), (5, 5), 1.5)
    chw = np.stack([plane] * 3) if gray else np.stack([plane, plane[::-1], 255 - plane])
    want = np.stack([_apply(np.ascontiguousarray(c), Geo, nearest=False) for c in chw])
    got = _apply_planes(chw, Geo)
    assert got.shape == (3, 40, 56) and got.dtype == np.uint8
    assert np.array_equal(got, want)
    assert gray == bool(np.array_equal(got[0], got[2]))
