"""The common reader options (pvslam_core.datasets.base): frame selection and the image transform.

Geometry is checked the way it is used: a known 3D point is projected with the intrinsics the reader reports,
and the image content must be at that pixel -- before and after undistort / resize / crop.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from pvslam_core.datasets.base import BaseReader, DatasetError, ReaderOptions
from pvslam_core.types import Category, Frame, Intrinsics, PanopticSegmentation, Segment

W, H = 160, 124
RAW = Intrinsics(150.0, 148.0, 81.3, 60.7, W, H, (-0.25, 0.08, 0.001, -0.0015, 0.0))
POINTS = np.array([[0.0, 0.0, 4.0], [-1.2, -0.8, 4.0], [1.3, 0.9, 5.0], [0.9, -0.9, 3.5], [-1.5, 0.7, 4.5]])
SIGMA = 2.0


def project(points: np.ndarray, k: Intrinsics) -> np.ndarray:
    import cv2

    K = k.matrix().numpy()
    dist = np.asarray(k.dist, dtype=np.float64) if k.dist else np.zeros(5)
    uv, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)
    return uv.reshape(-1, 2)


def blob_image(centres: np.ndarray) -> np.ndarray:
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    img = np.zeros((H, W), dtype=np.float64)
    for u, v in centres:
        img += np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * SIGMA**2))
    return np.clip(img * 255.0, 0, 255)


def centroid(img: np.ndarray, guess: np.ndarray, r: int = 6) -> np.ndarray:
    x0, y0 = int(round(guess[0])), int(round(guess[1]))
    win = img[max(y0 - r, 0) : y0 + r + 1, max(x0 - r, 0) : x0 + r + 1].astype(np.float64)
    win = np.clip(win - 0.05 * win.max(), 0, None)
    ys, xs = np.mgrid[max(y0 - r, 0) : y0 + r + 1, max(x0 - r, 0) : x0 + r + 1]
    return np.array([(win * xs).sum() / win.sum(), (win * ys).sum() / win.sum()])


class MemReader(BaseReader):
    """In-memory reader: blobs at the projections of POINTS, a labelled rectangle, depth = 2 + x/100."""

    def __init__(self, options: ReaderOptions, n: int = 20, intr: Intrinsics = RAW, loops=None):
        super().__init__(options)
        self.n, self.intr, self.loops, self.loaded = n, intr, loops, []
        gray = blob_image(project(POINTS, intr)).astype(np.uint8)
        self.image = torch.from_numpy(np.stack([gray] * 3)).contiguous()
        ids = np.zeros((H, W), dtype=np.int64)
        ids[30:90, 40:120] = 26001
        self.ids = torch.from_numpy(ids)
        self.depth = torch.from_numpy((2.0 + np.arange(W, dtype=np.float32) / 100.0)[None].repeat(H, 0))

    def _raw_count(self) -> int:
        return self.n

    def _raw_intrinsics(self) -> Intrinsics:
        return self.intr

    def _sequence_name(self) -> str:
        return "mem"

    def _categories(self):
        return [Category(26, "car", True)]

    def _loop_pairs(self):
        return self.loops

    def _load(self, raw_index: int) -> Frame:
        self.loaded.append(raw_index)
        pan = PanopticSegmentation(self.ids.clone(), [Segment(26001, 26, True)])
        return Frame(raw_index, raw_index * 0.1, self.image.clone(), self.intr, gt_depth=self.depth.clone(),
                     gt_panoptic=pan, gt_dynamic=self.ids > 0, name=f"{raw_index:04d}.png")


# ------------------------------------------------------------------------------------------------ options ----
@pytest.mark.parametrize(
    "kwargs", [{"stride": 0}, {"start": -1}, {"start": 5, "end": 5}, {"resize": (0, 10)}, {"crop_multiple": 0},
               {"bogus": 1}]
)
def test_invalid_options_are_rejected(kwargs):
    with pytest.raises(ValidationError):
        ReaderOptions(**kwargs)


def test_stride_start_end_select_raw_frames():
    r = MemReader(ReaderOptions(start=3, end=15, stride=4, crop_multiple=1, undistort=False))
    frames = list(r)
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.name for f in frames] == ["0003.png", "0007.png", "0011.png"]
    assert [round(f.timestamp, 6) for f in frames] == [0.3, 0.7, 1.1]
    assert r.info().num_frames == len(r) == 3
    assert r[-1].name == "0011.png" and r[1].index == 1
    with pytest.raises(IndexError):
        r[3]


@pytest.mark.parametrize("kwargs, msg", [({"start": 20}, "start=20"), ({"end": 21}, "end=21")])
def test_start_end_out_of_range(kwargs, msg):
    r = MemReader(ReaderOptions(**kwargs))
    with pytest.raises(DatasetError, match=msg):
        r.info()


def test_loop_pairs_are_remapped_to_output_indices():
    r = MemReader(ReaderOptions(start=2, stride=3), loops=[(17, 2), (18, 5), (1, 0), (14, 13)])
    # output k <-> raw 2 + 3k: 17 -> 5, 2 -> 0, 18 -> 5 (nearest), 5 -> 1; (1, 0) is before start; 14/13 collapse
    assert r.info().loop_pairs.tolist() == [[5, 0], [5, 1]]


# ----------------------------------------------------------------------------------------------- geometry ----
def _check_projection(frame: Frame, tol: float) -> None:
    img = frame.image[0].numpy()
    for X, uv in zip(POINTS, project(POINTS, frame.intrinsics)):
        got = centroid(img, uv)
        assert np.linalg.norm(got - uv) < tol, (X, uv, got, frame.intrinsics)


def test_raw_image_matches_raw_projection():
    r = MemReader(ReaderOptions(undistort=False, crop_multiple=1))
    f = r[0]
    assert f.intrinsics == RAW
    _check_projection(f, 0.05)


@pytest.mark.parametrize(
    "opts",
    [
        dict(undistort=True, crop_multiple=1),
        dict(undistort=True, crop_multiple=8),
        dict(undistort=True, resize=(80, 62), crop_multiple=8),
        dict(undistort=False, resize=(120, 93), crop_multiple=8),
        dict(undistort=True, resize=(240, 186), crop_multiple=16),
        dict(undistort=False, resize=(100, 100), crop_multiple=1),  # anisotropic
    ],
)
def test_transform_moves_pixels_exactly_as_intrinsics(opts):
    r = MemReader(ReaderOptions(**opts))
    info = r.info()
    f = r[0]
    k = f.intrinsics
    assert k == info.intrinsics
    assert (f.width, f.height) == (k.width, k.height)
    m = opts.get("crop_multiple", 8)
    assert k.width % m == 0 and k.height % m == 0
    if opts.get("undistort"):
        assert k.dist == () and not k.has_distortion
    else:
        assert k.dist == RAW.dist
    # measured errors are < 0.07 px; a half-pixel-centre slip in scaled() would give >= 0.125 px here
    _check_projection(f, 0.1)


def test_crop_is_centred_and_matches_intrinsics():
    r = MemReader(ReaderOptions(undistort=False, crop_multiple=16))
    k = r.info().intrinsics
    assert (k.width, k.height) == (160, 112)
    assert k.cx == pytest.approx(RAW.cx) and k.cy == pytest.approx(RAW.cy - 6)  # (124 - 112) / 2 rows cut on top
    f = r[0]
    assert torch.equal(f.image, r.image[:, 6:118, :])


def test_maps_follow_the_image():
    r = MemReader(ReaderOptions(undistort=True, resize=(100, 77), crop_multiple=8))
    f = r[0]
    assert f.gt_depth.shape == f.gt_dynamic.shape == f.gt_panoptic.ids.shape == (f.height, f.width)
    assert f.gt_depth.dtype == torch.float32 and f.gt_dynamic.dtype == torch.bool
    assert f.gt_panoptic.ids.dtype == torch.int64
    # nearest neighbour: no new values are invented
    assert set(torch.unique(f.gt_panoptic.ids).tolist()) <= {0, 26001}
    vals = set(np.unique(f.gt_depth.numpy()).tolist())
    assert vals <= set(np.unique(r.depth.numpy()).tolist()) | {0.0}
    assert torch.equal(f.gt_dynamic, f.gt_panoptic.ids > 0)
    # the labelled rectangle lands where the rectangle's corners project (through the same intrinsics)
    raw_corners = np.array([[40.0, 30.0], [119.0, 89.0]])
    import cv2

    und = cv2.undistortPoints(raw_corners[:, None], RAW.matrix().numpy(), np.asarray(RAW.dist)).reshape(-1, 2)
    k = f.intrinsics
    u = und[:, 0] * k.fx + k.cx
    v = und[:, 1] * k.fy + k.cy
    ys, xs = np.nonzero(f.gt_panoptic.ids.numpy() > 0)
    assert abs(xs.min() - u[0]) <= 1.5 and abs(xs.max() - u[1]) <= 1.5
    assert abs(ys.min() - v[0]) <= 1.5 and abs(ys.max() - v[1]) <= 1.5
    assert [s.id for s in f.gt_panoptic.segments] == [26001]


def test_identity_transform_keeps_tensors():
    intr = Intrinsics(100.0, 100.0, 79.5, 61.5, W, H)
    r = MemReader(ReaderOptions(crop_multiple=4), intr=intr)  # 160x124 are multiples of 4, no distortion
    f = r[0]
    assert f.intrinsics == intr and torch.equal(f.image, r.image)


def test_frame_size_mismatch_names_the_frame():
    class Bad(MemReader):
        def _load(self, i):
            f = super()._load(i)
            f.image = f.image[:, :-1]
            return f

    with pytest.raises(DatasetError, match="0000.png.*123"):
        Bad(ReaderOptions())[0]



def test_a_long_runs_revisit_pairs_cost_bytes_per_pair_not_python_objects(tmp_path):
    """A repeated loop's ground truth grows with the square of the laps (millions of pairs at 10 000 frames): the
    revisit file is written and read, and the reader maps it to output frames, without a Python object per pair."""
    import json
    import tracemalloc

    import numpy as np

    from pvslam_core.evaluation.loops import read_pairs_json, write_pairs_json

    rng = np.random.default_rng(0)
    n = 300_000
    pairs = np.stack([rng.integers(1000, 9000, n), rng.integers(0, 900, n)], 1)
    path = tmp_path / "loops.json"
    tracemalloc.start()

    def peak_of(fn):  # bytes allocated at the peak of fn() beyond what was held before
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        out = fn()
        return out, tracemalloc.get_traced_memory()[1] - before

    def write():
        with path.open("w") as f:
            write_pairs_json(f, pairs, source="synthetic")

    _, write_peak = peak_of(write)
    back, read_peak = peak_of(lambda: read_pairs_json(path))
    mapped, map_peak = peak_of(lambda: MemReader(ReaderOptions(start=0, stride=1), loops=back, n=9000).info().loop_pairs)
    tracemalloc.stop()
    assert json.loads(path.read_text())["pairs"][:3] == pairs[:3].tolist()
    assert back.dtype == np.int64 and np.array_equal(back, pairs)
    assert len(mapped) == len(np.unique(pairs, axis=0))
    # as a list of tuples (or JSON's list of lists) the pairs cost 150-250 bytes each
    assert max(write_peak, read_peak, map_peak) < 100 * n, (write_peak, read_peak, map_peak)
    # the writer holds a block of rows, never the whole text
    assert write_peak < path.stat().st_size / 2, (write_peak, path.stat().st_size)
