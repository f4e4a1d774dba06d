"""Reader of pvslam's synthetic layout (see :mod:`.writer`): frames with pose, depth, panoptic and dynamic GT.

:class:`SyntheticSequence` reads the folder as plain arrays (used by tests and tools); :class:`SyntheticReader`
is the :class:`~pvslam_core.datasets.base.BaseReader` of the ``synthetic`` plugin, which generates (or finds in
the cache) the configured scenario unless ``path`` names an existing folder.  The reader decodes only the
ground-truth maps its ``gt_maps`` option asks for (by default the panoptic labels: depth and dynamic masks are
two more PNGs per frame that only oracles and tests read).
"""
from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path
from typing import Iterable, Optional

import cv2
import numpy as np
import torch

from pvslam_core.datasets.base import BaseReader, DatasetError
from pvslam_core.evaluation.loops import read_pairs_json
from pvslam_core.types import Category, Frame, Intrinsics, PanopticSegmentation, Segment

from .config import SyntheticConfig


#: the per-frame ground-truth maps of the layout (besides the RGB image and the pose)
GT_MAPS = ("depth", "panoptic", "dynamic")


def _check_maps(maps: Iterable[str]) -> frozenset[str]:
    maps = frozenset(maps)
    unknown = sorted(maps - set(GT_MAPS))
    if unknown:
        raise ValueError(f"unknown ground-truth maps {unknown}; choose among {list(GT_MAPS)}")
    return maps


def _read_list(path: Path) -> list[tuple[float, list[str]]]:
    if not path.is_file():
        raise DatasetError(f"{path}: file missing")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        try:
            rows.append((float(parts[0]), parts[1:]))
        except ValueError as exc:
            raise DatasetError(f"{path}:{n}: cannot parse {line!r}") from exc
    return rows


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: frame listed but missing")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise DatasetError(f"{path}: unreadable or corrupt image")
    return img


class SyntheticSequence:
    """Array access to a synthetic folder."""

    def __init__(self, root: Path | str):
        self.root = Path(root)
        if not (self.root / "meta.json").is_file():
            raise DatasetError(f"{self.root / 'meta.json'}: missing; {self.root} is not a (complete) synthetic "
                               "sequence folder")
        self.meta = json.loads((self.root / "meta.json").read_text())
        self.depth_scale = float(self.meta.get("depth_scale", 5000.0))
        rgb = _read_list(self.root / "rgb.txt")
        self.timestamps = np.array([r[0] for r in rgb], np.float64)
        self.rgb_files = [r[1][0] for r in rgb]
        self.depth_files = [r[1][0] for r in _read_list(self.root / "depth.txt")]
        gt = _read_list(self.root / "groundtruth.txt")
        if len(gt) != len(rgb) or len(self.depth_files) != len(rgb):
            raise DatasetError(f"{self.root}: rgb.txt has {len(rgb)} frames but depth.txt {len(self.depth_files)} "
                               f"and groundtruth.txt {len(gt)}")
        if np.any(np.diff(self.timestamps) <= 0):
            raise DatasetError(f"{self.root / 'rgb.txt'}: timestamps not strictly increasing")
        self.poses = np.array([[float(x) for x in r[1]] for r in gt], np.float64)
        if self.poses.shape[1:] != (7,):
            raise DatasetError(f"{self.root / 'groundtruth.txt'}: expected 7 values after the timestamp")
        vals = (self.root / "calib.txt").read_text().split() if (self.root / "calib.txt").is_file() else []
        if len(vals) != 4:
            raise DatasetError(f"{self.root / 'calib.txt'}: expected 'fx fy cx cy', found {len(vals)} values")
        fx, fy, cx, cy = (float(v) for v in vals)
        try:
            self.intrinsics = Intrinsics(fx, fy, cx, cy, int(self.meta["width"]), int(self.meta["height"]))
        except ValueError as exc:
            raise DatasetError(f"{self.root / 'calib.txt'}: {exc}") from exc

    def __len__(self) -> int:
        return len(self.rgb_files)

    @cached_property
    def _panoptic(self) -> tuple[list[Category], np.ndarray, np.ndarray]:
        """``panoptic.json`` read once: the categories, every frame's segments as rows ``(id, category id,
        isthing)`` int64 ``[S, 3]``, and the first row of each frame ``[n + 1]`` (a dict per segment would cost
        ~2 kB a frame for the whole run)."""
        path = self.root / "panoptic.json"
        try:
            doc = json.loads(path.read_text())
            cats = [Category(int(c["id"]), str(c["name"]), bool(c["isthing"]), tuple(int(x) for x in c["color"]))
                    for c in doc["categories"]]
            infos = [f["segments_info"] for f in doc["frames"]]
            rows = np.array([(int(s["id"]), int(s["category_id"]), bool(s["isthing"])) for info in infos
                             for s in info], dtype=np.int64).reshape(-1, 3)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DatasetError(f"{path}: unreadable or not a pvslam panoptic.json ({exc!r})") from exc
        if len(infos) != len(self):
            raise DatasetError(f"{path}: {len(infos)} frames but rgb.txt lists {len(self)}")
        first = np.concatenate([[0], np.cumsum([len(info) for info in infos])]).astype(np.int64)
        return cats, rows, first

    @property
    def categories(self) -> list[Category]:
        return self._panoptic[0]

    @property
    def loop_pairs(self) -> np.ndarray:
        """Ground-truth revisits, int64 ``[M, 2]`` (``loops.json``, read on each call: the reader keeps only the
        pairs mapped to its frames; none when the folder has no such file)."""
        p = self.root / "loops.json"
        return read_pairs_json(p) if p.is_file() else np.zeros((0, 2), dtype=np.int64)

    def segments(self, i: int) -> list[Segment]:
        _, rows, first = self._panoptic
        return [Segment(int(sid), int(cat), bool(thing)) for sid, cat, thing in rows[first[i]:first[i + 1]].tolist()]

    def arrays(self, i: int, maps: Iterable[str] = GT_MAPS) -> dict[str, np.ndarray]:
        """``rgb`` uint8 [H,W,3], ``pose`` [7], and of the ground-truth ``maps`` asked for: ``depth`` float32
        metres, ``panoptic`` int64, ``dynamic`` bool (each one more PNG to decode)."""
        maps = _check_maps(maps)
        name = Path(self.rgb_files[i]).name
        out = {"rgb": cv2.cvtColor(_imread(self.root / self.rgb_files[i], cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB),
               "pose": self.poses[i]}
        if "depth" in maps:
            depth = _imread(self.root / self.depth_files[i], cv2.IMREAD_UNCHANGED)
            if depth.dtype != np.uint16:
                raise DatasetError(f"{self.root / self.depth_files[i]}: expected a 16-bit PNG, got {depth.dtype}")
            out["depth"] = depth.astype(np.float32) / np.float32(self.depth_scale)
        if "panoptic" in maps:
            # BGR as decoded: id = R + 256 G + 65536 B = bgr[2] + 256 bgr[1] + 65536 bgr[0]
            pan = _imread(self.root / "panoptic" / name, cv2.IMREAD_COLOR).astype(np.int64)
            out["panoptic"] = pan[..., 2] + 256 * pan[..., 1] + 65536 * pan[..., 0]
        if "dynamic" in maps:
            out["dynamic"] = _imread(self.root / "dynamic" / name, cv2.IMREAD_GRAYSCALE) > 127
        return out

    def frame(self, i: int, maps: Iterable[str] = GT_MAPS) -> Frame:
        a = self.arrays(i, maps)
        shape = (self.intrinsics.height, self.intrinsics.width)
        if a["rgb"].shape[:2] != shape:
            raise DatasetError(f"{self.root / self.rgb_files[i]}: image is {a['rgb'].shape[1]}x{a['rgb'].shape[0]} "
                               f"but meta.json says {shape[1]}x{shape[0]}")
        return Frame(
            index=i,
            timestamp=float(self.timestamps[i]),
            image=torch.from_numpy(np.ascontiguousarray(a["rgb"])).permute(2, 0, 1).contiguous(),
            intrinsics=self.intrinsics,
            gt_pose=torch.from_numpy(a["pose"].copy()),
            gt_depth=torch.from_numpy(a["depth"]) if "depth" in a else None,
            gt_panoptic=(PanopticSegmentation(ids=torch.from_numpy(a["panoptic"]), segments=self.segments(i))
                         if "panoptic" in a else None),
            gt_dynamic=torch.from_numpy(a["dynamic"]) if "dynamic" in a else None,
            name=Path(self.rgb_files[i]).name,
        )


class SyntheticReader(BaseReader):
    """``synthetic`` dataset plugin: generates/caches the scenario (or reads ``path``) and yields its frames."""

    def __init__(self, options: SyntheticConfig):
        super().__init__(options)
        self.options: SyntheticConfig = options
        self._seq: Optional[SyntheticSequence] = None

    @property
    def sequence(self) -> SyntheticSequence:
        if self._seq is None:
            o = self.options
            if o.path:
                root = Path(o.path).expanduser()
                if not root.is_dir():
                    raise DatasetError(f"{root}: synthetic sequence folder not found")
            else:
                from .generator import ensure_cached

                root = ensure_cached(o.scenario, num_frames=o.num_frames, width=o.width, height=o.height,
                                     seed=o.seed, progress=o.progress, laps=o.laps, hfov_deg=o.hfov_deg,
                                     domain=o.domain)
            self._seq = SyntheticSequence(root)
        return self._seq

    def _raw_count(self) -> int:
        return len(self.sequence)

    def _raw_intrinsics(self) -> Intrinsics:
        return self.sequence.intrinsics

    def _load(self, raw_index: int) -> Frame:
        return self.sequence.frame(raw_index, self.options.gt_maps)

    def _sequence_name(self) -> str:
        m = self.sequence.meta
        return f"synthetic-{m.get('scenario', 'unknown')}"

    def _categories(self) -> list[Category]:
        return self.sequence.categories

    def _loop_pairs(self) -> Optional[np.ndarray]:
        return self.sequence.loop_pairs

    def _has_gt(self) -> tuple[bool, bool, bool]:
        maps = self.options.gt_maps  # what the yielded frames carry
        return (True, "depth" in maps, "panoptic" in maps)

    def _source(self) -> str:
        return str(self.sequence.root)


def make_reader(config: SyntheticConfig, context=None) -> SyntheticReader:  # type: ignore[no-untyped-def]
    return SyntheticReader(config)


def detect(path: Path):  # type: ignore[no-untyped-def]
    """A folder written by ``pvslam synth`` (meta.json, rgb.txt, panoptic.json): more specific than TUM's rgb.txt."""
    from pvslam_core.datasets.detect import DatasetMatch

    if not all((path / n).is_file() for n in ("meta.json", "rgb.txt", "panoptic.json")):
        return None
    return DatasetMatch(1.0, {"path": str(path)}, f"synthetic sequence {path.resolve().name} (exact ground truth)")
