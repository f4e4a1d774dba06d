"""panoptic/segments.json follows the COCO panoptic format; the checker applies panopticapi's rules."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pvslam_core.evaluation.coco_panoptic import coco_panoptic_problems
from pvslam_core.outputs.panoptic_png import PanopticWriter, load_panoptic_dir
from pvslam_core.types import Category, PanopticSegmentation, Segment

CATS = [Category(1, "road", False, (128, 64, 128)), Category(2, "car", True, (0, 0, 142)),
        Category(3, "sky", False, (70, 130, 180))]


def _tricky_frames():
    """Ids above 2^16 and 2^8 per channel, a map id without a Segment, a Segment absent from the map, a repeated
    Segment id and a category missing from CATS."""
    h, w = 10, 14
    frames = []
    for t in range(3):
        ids = np.ones((h, w), np.int64)
        ids[:3] = 3_000_000 + t * 256  # sky: a large id exercising all three channels
        ids[5:8, 2 + t : 6 + t] = 70_001  # a car moving right
        ids[8:, 10:] = 424242  # no Segment for this id: must become void
        ids[0, 0] = 0
        segs = [Segment(1, 1, False, 0.8), Segment(3_000_000 + t * 256, 3, False), Segment(70_001, 2, True, 0.6),
                Segment(70_001, 1, False),  # repeated id: the first wins
                Segment(555, 2, True),  # not in the map
                ]
        if t == 2:
            ids[0, 5:8] = 9
            segs.append(Segment(9, 77, True))  # category 77 is not in CATS: declared from the segments
        frames.append(PanopticSegmentation(torch.from_numpy(ids), segs))
    return frames


def _write(tmp_path, categories, frames):
    with PanopticWriter(tmp_path, categories=categories) as w:
        for t, seg in enumerate(frames):
            w.write(10 + t, seg, image_name=f"img_{t:03d}.jpg")
    return tmp_path / "panoptic"


@pytest.mark.parametrize("categories", [CATS, None])
def test_writer_output_obeys_coco_panoptic_rules(tmp_path, categories):
    frames = _tricky_frames()
    pan = _write(tmp_path, categories, frames)
    assert coco_panoptic_problems(pan, stuff_once=True) == []
    meta = json.loads((pan / "segments.json").read_text())
    assert [im["id"] for im in meta["images"]] == [10, 11, 12]
    assert meta["images"][0] == {"id": 10, "file_name": "img_000.jpg", "width": 14, "height": 10}
    ann = meta["annotations"][0]
    assert set(ann) == {"image_id", "file_name", "segments_info"} and ann["file_name"] == "000010.png"
    car = next(s for s in ann["segments_info"] if s["id"] == 70_001)
    assert car == {"id": 70_001, "category_id": 2, "iscrowd": 0, "bbox": [2, 5, 4, 3], "area": 12}
    assert {s["id"] for s in ann["segments_info"]} == {1, 3_000_000, 70_001}
    cats = {c["id"]: c for c in meta["categories"]}
    assert set(cats) == {1, 2, 3, 77}
    assert cats[2]["isthing"] == 1 and cats[2]["supercategory"] == "thing" and cats[1]["supercategory"] == "stuff"
    if categories:
        assert cats[3] == {"id": 3, "name": "sky", "isthing": 0, "supercategory": "stuff", "color": [70, 130, 180]}
    assert cats[77]["name"] == "category_77" and cats[77]["isthing"] == 1
    # pvslam's extras live under their own key
    assert meta["pvslam"]["segment_scores"]["10"] == {"1": 0.8, "3000000": 1.0, "70001": 0.6}
    # and read back: void where no segment, the scores restored
    back = load_panoptic_dir(pan)
    assert sorted(back) == [10, 11, 12]
    ids0 = frames[0].ids.numpy().copy()
    ids0[ids0 == 424242] = 0
    np.testing.assert_array_equal(back[10].ids.numpy(), ids0)
    assert back[10].segment(70_001).score == pytest.approx(0.6) and back[10].segment(70_001).isthing


def test_old_format_is_still_read(tmp_path):
    from pvslam_core.outputs.panoptic_png import save_panoptic

    seg = _tricky_frames()[0]
    (tmp_path / "panoptic").mkdir()
    info = save_panoptic(tmp_path / "panoptic" / "000004.png", seg)
    for d in info:
        d["score"], d["isthing"] = 0.5, d["category_id"] == 2
    (tmp_path / "panoptic" / "segments.json").write_text(json.dumps(
        {"annotations": [{"frame_index": 4, "file_name": "000004.png", "segments_info": info}],
         "categories": [{"id": 1, "name": "road", "isthing": 0}, {"id": 2, "name": "car", "isthing": 1},
                        {"id": 3, "name": "sky", "isthing": 0}]}))
    back = load_panoptic_dir(tmp_path / "panoptic")
    assert list(back) == [4] and back[4].segment(70_001).score == 0.5


def _mutate(pan, fn):
    meta = json.loads((pan / "segments.json").read_text())
    fn(meta)
    (pan / "segments.json").write_text(json.dumps(meta))


@pytest.mark.parametrize("breakage, message", [
    (lambda m: m["annotations"][0]["segments_info"].pop(0), "presented in PNG and not presented in JSON"),
    (lambda m: m["annotations"][0]["segments_info"].append(dict(m["annotations"][0]["segments_info"][0], id=5)),
     "presented in JSON and not presented in PNG"),
    (lambda m: m["annotations"][0]["segments_info"].append(m["annotations"][0]["segments_info"][0]),
     "listed more than once"),
    (lambda m: m["annotations"][0]["segments_info"][0].update(area=1), "area 1 but"),
    (lambda m: m["annotations"][0]["segments_info"][0].update(bbox=[0, 0, 1, 1]), "bbox"),
    (lambda m: m["annotations"][0]["segments_info"][0].update(category_id=99), "unknown category_id 99"),
    (lambda m: m["categories"][0].pop("supercategory"), "missing ['supercategory']"),
    (lambda m: m["categories"].append(m["categories"][0]), "declared twice"),
    (lambda m: m["annotations"][0].update(image_id=999), "image_id not in images"),
    (lambda m: m["images"][0].update(width=99), "PNG is 14x10"),
    (lambda m: m["annotations"][0]["segments_info"][0].pop("iscrowd"), "misses ['iscrowd']"),
])
def test_checker_catches_each_rule(tmp_path, breakage, message):
    pan = _write(tmp_path, CATS, _tricky_frames())
    _mutate(pan, breakage)
    probs = coco_panoptic_problems(pan)
    assert any(message in p for p in probs), probs


def test_checker_catches_a_wrong_rgb_encoding(tmp_path):
    from PIL import Image

    pan = _write(tmp_path, CATS, _tricky_frames())
    rgb = np.asarray(Image.open(pan / "000010.png").convert("RGB"))
    Image.fromarray(np.ascontiguousarray(rgb[..., ::-1])).save(pan / "000010.png")  # BGR instead of RGB
    probs = coco_panoptic_problems(pan)
    assert any("presented in PNG and not presented in JSON" in p for p in probs), probs


def test_checker_catches_two_segments_of_one_stuff_category(tmp_path):
    ids = torch.ones(4, 4, dtype=torch.int64)
    ids[2:] = 2
    seg = PanopticSegmentation(ids, [Segment(1, 1, False), Segment(2, 1, False)])
    with PanopticWriter(tmp_path, categories=CATS) as w:
        w.write(0, seg)
    assert coco_panoptic_problems(tmp_path / "panoptic") == []
    assert any("stuff category 1" in p for p in coco_panoptic_problems(tmp_path / "panoptic", stuff_once=True))
