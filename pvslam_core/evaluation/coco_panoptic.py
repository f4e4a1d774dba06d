"""Check a ``panoptic/`` folder against the rules of the COCO panoptic format and evaluation.

These are the checks ``panopticapi`` (``pq_compute`` and its format converters) applies to a prediction folder,
reimplemented here so that a run's output can be verified without that package:

* ``segments.json`` has ``images``, ``annotations`` and ``categories``; category ids are unique and carry ``name``,
  ``isthing`` (0/1), ``supercategory`` and ``color`` (RGB); image ids are unique with ``width``/``height``;
* every annotation names an image (``image_id``) and a PNG (``file_name``) that exists, is 8-bit RGB with the
  image's size, and encodes ``id = R + 256 G + 256^2 B`` (0 = void);
* the non-void ids in the PNG are exactly the ``segments_info`` ids ("presented in PNG and not presented in JSON"
  and the reverse are errors), each id once, with a declared ``category_id``, ``iscrowd`` in {0, 1}, and ``area``
  and ``bbox`` equal to the PNG's pixel count and box;
* optionally (``stuff_once``), a stuff category has at most one segment per image, as COCO's own files do.

The PNG is decoded with Pillow, independently of the OpenCV writer.
"""
from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

__all__ = ["coco_panoptic_problems"]

_CATEGORY_KEYS = ("id", "name", "isthing", "supercategory", "color")
_SEGMENT_KEYS = ("id", "category_id", "iscrowd", "bbox", "area")


def _read_rgb_ids(path: str) -> tuple[np.ndarray, str]:
    from PIL import Image

    with Image.open(path) as im:
        mode = im.mode
        rgb = np.asarray(im.convert("RGB")).astype(np.int64)
    return rgb[..., 0] + 256 * rgb[..., 1] + 65536 * rgb[..., 2], mode


def coco_panoptic_problems(panoptic_dir: str | os.PathLike, stuff_once: bool = False) -> list[str]:
    """Every violation of the COCO panoptic rules in ``panoptic_dir`` (``segments.json`` + PNGs); [] when valid."""
    d = os.fspath(panoptic_dir)
    try:
        with open(os.path.join(d, "segments.json"), encoding="utf-8") as f:
            meta: dict[str, Any] = json.load(f)
    except (OSError, ValueError) as exc:
        return [f"segments.json: cannot read: {exc}"]
    probs: list[str] = []
    for key in ("images", "annotations", "categories"):
        if not isinstance(meta.get(key), list):
            probs.append(f"segments.json: missing list {key!r}")
    if probs:
        return probs
    cats = _categories(meta["categories"], probs)
    images = _images(meta["images"], probs)
    seen_images: set = set()
    for ann in meta["annotations"]:
        iid = ann.get("image_id")
        where = f"annotation {ann.get('file_name')} (image {iid})"
        if iid not in images:
            probs.append(f"{where}: image_id not in images")
        if iid in seen_images:
            probs.append(f"{where}: a second annotation for the same image")
        seen_images.add(iid)
        _check_annotation(d, ann, where, images.get(iid, {}), cats, stuff_once, probs)
    return probs


def _categories(categories: list, probs: list[str]) -> dict[int, dict]:
    """``{id: category}``; appends the problems of the declarations to ``probs``."""
    cats: dict[int, dict] = {}
    for c in categories:
        missing = [k for k in _CATEGORY_KEYS if k not in c]
        if missing:
            probs.append(f"category {c.get('id')}: missing {missing}")
        if c.get("id") in cats:
            probs.append(f"category id {c['id']} declared twice")
        if c.get("isthing") not in (0, 1):
            probs.append(f"category {c.get('id')}: isthing must be 0 or 1, got {c.get('isthing')!r}")
        col = c.get("color")
        if not (isinstance(col, list) and len(col) == 3 and all(isinstance(v, int) and 0 <= v <= 255 for v in col)):
            probs.append(f"category {c.get('id')}: color must be [r, g, b] in 0..255, got {col!r}")
        cats[c.get("id")] = c
    return cats


def _images(images_list: list, probs: list[str]) -> dict[int, dict]:
    """``{id: image}``; appends the problems of the image entries to ``probs``."""
    images: dict[int, dict] = {}
    for im in images_list:
        if not all(k in im for k in ("id", "file_name", "width", "height")):
            probs.append(f"image {im.get('id')}: needs id, file_name, width, height")
        if im.get("id") in images:
            probs.append(f"image id {im['id']} listed twice")
        images[im.get("id")] = im
    return images


def _check_annotation(d: str, ann: dict, where: str, im: dict, cats: dict[int, dict], stuff_once: bool,
                      probs: list[str]) -> None:
    """The problems of one annotation against its PNG (size, mode, ids, areas, boxes), appended to ``probs``."""
    path = os.path.join(d, str(ann.get("file_name")))
    if not os.path.isfile(path):
        probs.append(f"{where}: PNG not found")
        return
    ids, mode = _read_rgb_ids(path)
    if mode != "RGB":
        probs.append(f"{where}: PNG mode {mode}, expected 8-bit RGB")
    if im and (ids.shape[1], ids.shape[0]) != (im.get("width"), im.get("height")):
        probs.append(f"{where}: PNG is {ids.shape[1]}x{ids.shape[0]}, image says {im.get('width')}x"
                     f"{im.get('height')}")
    present, counts = np.unique(ids, return_counts=True)
    area = {int(i): int(n) for i, n in zip(present, counts) if i != 0}
    segs = ann.get("segments_info", [])
    json_ids = [s.get("id") for s in segs]
    dup = sorted({i for i in json_ids if json_ids.count(i) > 1})
    if dup:
        probs.append(f"{where}: segment ids listed more than once: {dup}")
    only_png = sorted(set(area) - set(json_ids))
    only_json = sorted(set(json_ids) - set(area))
    if only_png:
        probs.append(f"{where}: ids {only_png} are presented in PNG and not presented in JSON")
    if only_json:
        probs.append(f"{where}: ids {only_json} are presented in JSON and not presented in PNG")
    stuff_seen: dict[int, int] = {}
    for s in segs:
        missing = [k for k in _SEGMENT_KEYS if k not in s]
        if missing:
            probs.append(f"{where}: segment {s.get('id')} misses {missing}")
            continue
        sid, cid = s["id"], s["category_id"]
        if cid not in cats:
            probs.append(f"{where}: segment {sid} has unknown category_id {cid}")
        elif stuff_once and not cats[cid]["isthing"]:
            if cid in stuff_seen:
                probs.append(f"{where}: stuff category {cid} has segments {stuff_seen[cid]} and {sid}")
            stuff_seen[cid] = sid
        if s["iscrowd"] not in (0, 1):
            probs.append(f"{where}: segment {sid}: iscrowd must be 0 or 1")
        if sid in area:
            if s["area"] != area[sid]:
                probs.append(f"{where}: segment {sid}: area {s['area']} but {area[sid]} pixels in the PNG")
            ys, xs = np.nonzero(ids == sid)
            box = [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]
            if list(s["bbox"]) != box:
                probs.append(f"{where}: segment {sid}: bbox {s['bbox']} but the PNG gives {box}")
