"""``segments_info`` / ``coco_ids`` (per-(segment, row/column) bincounts over a lookup-table labelling) against the
sort-based implementation they replaced, kept here as the reference; and the writer's journal lines, encoded
directly, against the sanitising ``to_jsonable`` walk."""
import json
import math

import numpy as np
import pytest
import torch

from pvslam_core.outputs import panoptic_png as pp
from pvslam_core.outputs.metrics import to_jsonable
from pvslam_core.types import PanopticSegmentation, Segment


def ref_coco_ids(seg):
    ids = seg.ids.numpy().astype(np.int64)
    known = np.array(sorted({int(s.id) for s in seg.segments} - {0}), dtype=np.int64)
    return np.where(np.isin(ids, known), ids, 0)


def ref_segments_info(seg):
    ids = ref_coco_ids(seg)
    h, w = ids.shape
    present, inv, counts = np.unique(ids.reshape(-1), return_inverse=True, return_counts=True)
    order = np.argsort(inv.reshape(-1), kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    xs, ys = order % w, order // w
    x0, x1 = np.minimum.reduceat(xs, starts), np.maximum.reduceat(xs, starts)
    y0, y1 = np.minimum.reduceat(ys, starts), np.maximum.reduceat(ys, starts)
    row = {int(v): k for k, v in enumerate(present.tolist())}
    out, seen = [], set()
    for s in seg.segments:
        if int(s.id) in seen:
            continue
        seen.add(int(s.id))
        k = row.get(int(s.id))
        if int(s.id) == 0 or k is None:
            continue
        out.append({"id": int(s.id), "category_id": int(s.category_id), "iscrowd": 0,
                    "bbox": [int(x0[k]), int(y0[k]), int(x1[k] - x0[k] + 1), int(y1[k] - y0[k] + 1)],
                    "area": int(counts[k])})
    return out


def random_segmentations(big: bool):
    rng = np.random.default_rng(1 if big else 0)
    for _ in range(25):
        h, w = rng.integers(1, 30, size=2)
        stride = 10_000_000 if big else 1000  # big: ids above the lookup-table range (binary-search path)
        ids = rng.integers(0, 9, size=(h, w)) * stride + rng.integers(0, 3, size=(h, w))
        choice = rng.choice(np.unique(ids), size=min(5, len(np.unique(ids))), replace=False)
        segs = [Segment(int(v), int(v) // stride + 1, bool(v % 2), 0.5) for v in choice]
        segs += [Segment(424242, 3, False, 1.0), Segment(0, 1, False, 1.0)]  # absent id, void id
        yield PanopticSegmentation(ids=torch.from_numpy(ids), segments=segs + segs[:1])  # a repeated id


@pytest.mark.parametrize("big", [False, True])
def test_segments_info_equals_sort_based_reference(big, caplog):
    n = 0
    for seg in random_segmentations(big):
        assert np.array_equal(pp.coco_ids(seg), ref_coco_ids(seg))
        got = pp.segments_info(seg)
        assert got == ref_segments_info(seg)
        n += len(got)
    assert n > 40  # the cases are not all empty


def test_segments_info_full_frame_and_empty():
    ids = np.full((24, 32), 7000, dtype=np.int64)
    ids[3:9, 5:12] = 7001
    seg = PanopticSegmentation(ids=torch.from_numpy(ids), segments=[Segment(7000, 7, False), Segment(7001, 7, True)])
    assert pp.segments_info(seg) == [
        {"id": 7000, "category_id": 7, "iscrowd": 0, "bbox": [0, 0, 32, 24], "area": 24 * 32 - 42},
        {"id": 7001, "category_id": 7, "iscrowd": 0, "bbox": [5, 3, 7, 6], "area": 42}]
    none = PanopticSegmentation(ids=torch.zeros(4, 5, dtype=torch.int64), segments=[])
    assert pp.segments_info(none) == [] and not pp.coco_ids(none).any()


def test_journal_lines_encode_like_to_jsonable(tmp_path):
    """The journal encodes its (str-keyed, plain) lines directly; a NaN score or numpy values take the walk."""
    w = pp.PanopticWriter(str(tmp_path), categories=None, journal=True)
    ids = np.full((4, 6), 2000, dtype=np.int64)
    ids[1:3, 1:3] = 1001
    w.write(0, PanopticSegmentation(ids=torch.from_numpy(ids), segments=[Segment(2000, 2, False, 0.25),
                                                                          Segment(1001, 1, True, 0.75)]))
    w.write(1, PanopticSegmentation(ids=torch.from_numpy(ids), segments=[Segment(2000, 2, False, float("nan")),
                                                                          Segment(1001, 1, True, 1.0)]))
    w._journal_line({"numpy": np.float32(0.5), "ints": np.arange(3)})
    w._journal.flush()
    lines = (tmp_path / "panoptic" / pp.JOURNAL).read_text().splitlines()
    objs = [json.loads(s) for s in lines]
    for s, o in zip(lines[1:3], objs[1:3]):
        assert s == json.dumps(to_jsonable(o), separators=(",", ":"), allow_nan=False)
    assert objs[1]["scores"] == {"2000": 0.25, "1001": 0.75}
    assert objs[2]["scores"]["2000"] is None and objs[2]["scores"]["1001"] == 1.0  # NaN -> null
    assert objs[3] == {"numpy": 0.5, "ints": [0, 1, 2]}
    assert not any(isinstance(v, float) and math.isnan(v) for v in objs[2]["scores"].values())
    w.close()
