"""COCO panoptic PNGs (``id = R + 256 G + 256^2 B``, 0 = void), their ``segments.json``, and colour visualisation.

Run directory layout written by :class:`PanopticWriter`::

    run_dir/panoptic/000000.png ...        COCO panoptic id PNG of each written frame
    run_dir/panoptic/segments.json         {"annotations": [{"frame_index", "file_name", "segments_info"}],
                                            "categories": [...]}   (COCO panoptic style)
    run_dir/panoptic_vis/000000.png ...    colour visualisation (optional)
"""
from __future__ import annotations

import json
import os
from typing import Any, Optional, Sequence

import numpy as np

from ._atomic import atomic_write_bytes
from .metrics import write_json_atomic

__all__ = [
    "MAX_ID",
    "encode_ids",
    "decode_ids",
    "save_panoptic",
    "load_panoptic",
    "segments_info",
    "colorize",
    "PanopticWriter",
    "load_panoptic_dir",
]

MAX_ID = 256**3 - 1


def _np(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def encode_ids(ids: Any) -> np.ndarray:
    """int ids ``[H, W]`` (0 <= id < 2^24) -> ``uint8 [H, W, 3]`` RGB with ``id = R + 256 G + 256^2 B``."""
    a = _np(ids).astype(np.int64)
    if a.ndim != 2:
        raise ValueError(f"encode_ids: ids must be [H, W], got {a.shape}")
    if a.size and (a.min() < 0 or a.max() > MAX_ID):
        raise ValueError(f"encode_ids: ids must be in [0, {MAX_ID}], got range [{a.min()}, {a.max()}]")
    out = np.empty(a.shape + (3,), dtype=np.uint8)
    out[..., 0] = a & 0xFF
    out[..., 1] = (a >> 8) & 0xFF
    out[..., 2] = (a >> 16) & 0xFF
    return out


def decode_ids(rgb: Any) -> np.ndarray:
    """``uint8 [H, W, 3]`` RGB -> int64 ids ``[H, W]``."""
    a = _np(rgb)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise ValueError(f"decode_ids: expected [H, W, 3], got {a.shape}")
    a = a.astype(np.int64)
    return a[..., 0] + 256 * a[..., 1] + 65536 * a[..., 2]


def _png_bytes(rgb: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))  # OpenCV writes BGR
    if not ok:
        raise IOError("PNG encoding failed")
    return buf.tobytes()


def _read_png_rgb(path: str) -> np.ndarray:
    import cv2

    bgr = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if bgr is None:
        raise FileNotFoundError(f"cannot read PNG {path}")
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise ValueError(f"{path}: a panoptic PNG must be 8-bit RGB, got shape {bgr.shape} dtype {bgr.dtype}")
    return bgr[..., ::-1]


def segments_info(seg) -> list[dict]:
    """COCO-style ``segments_info`` of a :class:`~pvslam_core.types.PanopticSegmentation` (segments present in the
    id map, with ``area`` and ``bbox`` [x, y, w, h])."""
    ids = _np(seg.ids).astype(np.int64)
    present, areas = np.unique(ids, return_counts=True)
    area = dict(zip(present.tolist(), areas.tolist()))
    out = []
    for s in seg.segments:
        sid = int(s.id)
        if sid == 0 or sid not in area:
            continue
        ys, xs = np.nonzero(ids == sid)
        out.append(
            {
                "id": sid,
                "category_id": int(s.category_id),
                "isthing": int(bool(s.isthing)),
                "score": float(s.score),
                "area": int(area[sid]),
                "bbox": [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)],
            }
        )
    return out


def save_panoptic(path: str | os.PathLike, seg) -> list[dict]:
    """Write ``seg.ids`` as a COCO panoptic PNG (atomically); returns its ``segments_info``."""
    atomic_write_bytes(path, _png_bytes(encode_ids(seg.ids)))
    return segments_info(seg)


def load_panoptic(path: str | os.PathLike, segments_info: Sequence[Any], categories: Optional[Any] = None):
    """Read a COCO panoptic PNG into a :class:`~pvslam_core.types.PanopticSegmentation`.

    ``segments_info``: COCO dicts (``id``, ``category_id``, optional ``isthing``/``score``) or ``Segment`` objects;
    ``isthing`` comes from ``categories`` when given.
    """
    import torch

    from pvslam_core.types import PanopticSegmentation, Segment

    ids = decode_ids(_read_png_rgb(os.fspath(path)))
    thing = {}
    if categories is not None:
        for c in categories.values() if isinstance(categories, dict) else categories:
            cid = c["id"] if isinstance(c, dict) else c.id
            thing[int(cid)] = bool(c["isthing"] if isinstance(c, dict) else c.isthing)
    segs = []
    for s in segments_info:
        if isinstance(s, dict):
            cat = int(s["category_id"])
            segs.append(
                Segment(int(s["id"]), cat, thing.get(cat, bool(s.get("isthing", False))), float(s.get("score", 1.0)))
            )
        else:
            segs.append(s)
    return PanopticSegmentation(ids=torch.from_numpy(ids), segments=segs)


# ----------------------------------------------------------------------------------------------------------------
# visualisation
# ----------------------------------------------------------------------------------------------------------------
def _shade(color: np.ndarray, sid: np.ndarray) -> np.ndarray:
    """Distinct, time-stable shades of ``color [M, 3]`` for instance ids ``sid [M]`` (deterministic hash)."""
    h = (sid.astype(np.uint64) * np.uint64(2654435761)) % np.uint64(2**32)
    jit = np.stack([(h >> np.uint64(s)) & np.uint64(0xFF) for s in (0, 8, 16)], axis=-1).astype(np.int64)
    jit = (jit * 100) // 255 - 50  # [-50, 50] per channel
    return np.clip(color.astype(np.int64) + jit, 0, 255).astype(np.uint8)


def colorize(seg, categories: Any, void_color=(0, 0, 0)) -> np.ndarray:
    """``uint8 [H, W, 3]`` RGB: stuff in its category colour, thing instances in distinct shades of theirs
    (stable over time: the shade depends on the id only), void in ``void_color``."""
    cat_color: dict[int, tuple[int, int, int]] = {}
    for c in categories.values() if isinstance(categories, dict) else categories:
        cid = c["id"] if isinstance(c, dict) else c.id
        col = c.get("color", (128, 128, 128)) if isinstance(c, dict) else c.color
        cat_color[int(cid)] = tuple(int(v) for v in col)
    ids = _np(seg.ids).astype(np.int64)
    uniq, inv = np.unique(ids, return_inverse=True)
    lut = np.zeros((len(uniq), 3), dtype=np.uint8)
    by_id = {int(s.id): s for s in seg.segments}
    for k, sid in enumerate(uniq.tolist()):
        s = by_id.get(sid)
        if sid == 0 or s is None:
            lut[k] = void_color
            continue
        base = np.array(cat_color.get(int(s.category_id), (128, 128, 128)), dtype=np.uint8)
        lut[k] = _shade(base[None], np.array([sid]))[0] if s.isthing else base
    return lut[inv.reshape(ids.shape)]


# ----------------------------------------------------------------------------------------------------------------
# run-directory writer
# ----------------------------------------------------------------------------------------------------------------
class PanopticWriter:
    """Writes ``run_dir/panoptic/{frame:06d}.png`` per frame and ``panoptic/segments.json`` (rewritten atomically
    on :meth:`flush` / :meth:`close`, and every ``flush_every`` frames). With ``categories`` and ``vis=True`` it
    also writes ``run_dir/panoptic_vis/{frame:06d}.png`` colour images."""

    def __init__(
        self,
        run_dir: str | os.PathLike,
        categories: Optional[Any] = None,
        vis: bool = False,
        flush_every: int = 50,
    ):
        self.run_dir = os.fspath(run_dir)
        self.dir = os.path.join(self.run_dir, "panoptic")
        self.vis_dir = os.path.join(self.run_dir, "panoptic_vis")
        os.makedirs(self.dir, exist_ok=True)
        self.categories = categories
        self.vis = bool(vis) and categories is not None
        if self.vis:
            os.makedirs(self.vis_dir, exist_ok=True)
        self.flush_every = int(flush_every)
        self.annotations: dict[int, dict] = {}
        self._since_flush = 0

    def write(self, frame_index: int, seg) -> str:
        """Write one frame (a later write of the same index replaces it). Returns the PNG path."""
        name = f"{int(frame_index):06d}.png"
        path = os.path.join(self.dir, name)
        info = save_panoptic(path, seg)
        if self.vis:
            atomic_write_bytes(os.path.join(self.vis_dir, name), _png_bytes(colorize(seg, self.categories)))
        self.annotations[int(frame_index)] = {"frame_index": int(frame_index), "file_name": name, "segments_info": info}
        self._since_flush += 1
        if self.flush_every > 0 and self._since_flush >= self.flush_every:
            self.flush()
        return path

    def _categories_json(self) -> list[dict]:
        if self.categories is None:
            return []
        out = []
        for c in self.categories.values() if isinstance(self.categories, dict) else self.categories:
            if isinstance(c, dict):
                out.append(dict(c))
            else:
                out.append({"id": int(c.id), "name": c.name, "isthing": int(c.isthing), "color": list(c.color)})
        return out

    def flush(self) -> None:
        write_json_atomic(
            os.path.join(self.dir, "segments.json"),
            {
                "annotations": [self.annotations[k] for k in sorted(self.annotations)],
                "categories": self._categories_json(),
            },
        )
        self._since_flush = 0

    def close(self) -> None:
        self.flush()

    def __enter__(self) -> "PanopticWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            self.flush()
        except Exception:
            if exc_type is None:
                raise
        return False


def load_panoptic_dir(panoptic_dir: str | os.PathLike, categories: Optional[Any] = None,
                      frames: Optional[Any] = None) -> dict[int, Any]:
    """``{frame_index: PanopticSegmentation}`` from a ``panoptic/`` folder written by :class:`PanopticWriter`
    (only the frame indices in ``frames`` when given, to bound memory)."""
    panoptic_dir = os.fspath(panoptic_dir)
    with open(os.path.join(panoptic_dir, "segments.json"), "r", encoding="utf-8") as f:
        meta = json.load(f)
    if categories is None and meta.get("categories"):
        categories = meta["categories"]
    out = {}
    for ann in meta.get("annotations", []):
        if frames is not None and int(ann["frame_index"]) not in frames:
            continue
        out[int(ann["frame_index"])] = load_panoptic(
            os.path.join(panoptic_dir, ann["file_name"]), ann["segments_info"], categories
        )
    return out
