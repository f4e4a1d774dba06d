"""Virtual KITTI 2 reader (rgb, depth, class + instance segmentation -> panoptic, camera poses).

Layout (Cabon, Murray, Humenberger, "Virtual KITTI 2", 2020; the archives ``vkitti_2.0.3_{rgb,depth,
classSegmentation,instanceSegmentation,textgt}.tar`` unpacked into one root, or each into its own folder
under the root -- both are found)::

    SceneNN/<variation>/frames/rgb/Camera_0/rgb_00000.jpg
    SceneNN/<variation>/frames/depth/Camera_0/depth_00000.png            uint16 centimetres, 65535 = sky / far
    SceneNN/<variation>/frames/classSegmentation/Camera_0/classgt_00000.png       RGB colour per class (colors.txt)
    SceneNN/<variation>/frames/instanceSegmentation/Camera_0/instancegt_00000.png 8-bit palette: trackID + 1, 0 = none
    SceneNN/<variation>/intrinsic.txt   header "frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]"
    SceneNN/<variation>/extrinsic.txt   header "frame cameraID r1,1 r1,2 r1,3 t1 r2,1 ... t3 0 0 0 1":
                                        the 4x4 world-to-camera matrix, row-major, per frame and camera
    SceneNN/<variation>/colors.txt      header "Category r g b", then e.g. "Car 255 127 80"
    SceneNN/<variation>/bbox.txt        "frame cameraID trackID left right top bottom number_pixels
                                        truncation_ratio occupancy_ratio isMoving" (used for the dynamic mask)

Sources used for these formats (read, not copied): the file headers quoted in public VKITTI2 loaders -- e.g.
DynoSAM ``VirtualKittiDataProvider.cpp`` (extrinsic/bbox/pose headers, 18 extrinsic columns ending "0 0 0 1"),
PVO ``tools/datasets/1_generate_image_info.py`` (class colours -> categories, instance PNG read through PIL as
palette indices, things = Truck/Car/Van, panoptic = category * 1000 + instance) and PVO ``data_readers/vkitti2.py``
(depth PNG / 100 = metres, intrinsics 725.0087 725.0087 620.5 187 for 1242x375).

Panoptic ids: category ids are 1 + the row of the class in colors.txt ("Undefined" is void, 0); stuff pixels get
``category_id * 1000``, thing pixels (Car, Van, Truck) ``category_id * 1000 + (trackID + 1)``; a thing pixel
without an instance is void.  The dynamic mask holds the instances that bbox.txt flags ``isMoving``.

Config example (plus the common options stride/start/end/resize/crop_multiple/undistort)::

    [dataset]
    plugin = "vkitti2"
    path = "/data/vkitti2"
    scene = "Scene01"
    variation = "clone"
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import torch

from pvslam_core.datasets.base import BaseReader, DatasetError
from pvslam_core.datasets.io import image_size, read_depth_png, read_raw, read_rgb
from pvslam_core.types import Category, Frame, Intrinsics, PanopticSegmentation, Segment

from .config import Vkitti2Config

THINGS = ("Car", "Van", "Truck")
VOID_CLASSES = ("Undefined",)
DEPTH_INVALID = 65535


def _ints(path: Path, parts: list[str], n: int) -> list[int]:
    try:
        return [int(v) for v in parts[:n]]
    except ValueError:
        raise DatasetError(f"{path}: expected integer frame/camera ids, got {' '.join(parts[:n])!r}") from None


def _table(path: Path, min_cols: int, exact: bool = False) -> list[list[str]]:
    """Whitespace table with a header line (skipped) -> rows of strings; errors name the file and line."""
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts or lineno == 1 and not parts[0].lstrip("-").isdigit():
            continue  # header / blank
        if len(parts) < min_cols or exact and len(parts) != min_cols:
            raise DatasetError(f"{path}:{lineno}: expected {min_cols} values, found {len(parts)}")
        rows.append(parts)
    return rows


def read_colors(path: Path) -> list[Category]:
    cats = []
    for parts in _table(path, 4):
        name = parts[0]
        try:
            rgb = tuple(int(v) for v in parts[1:4])
        except ValueError:
            raise DatasetError(f"{path}: bad colour for {name!r}: {parts[1:4]}") from None
        if name in VOID_CLASSES:
            continue
        cats.append(Category(id=len(cats) + 1, name=name, isthing=name in THINGS, color=rgb))  # type: ignore[arg-type]
    if not cats:
        raise DatasetError(f"{path}: no classes")
    return cats


def read_extrinsics(path: Path, camera: int) -> dict[int, np.ndarray]:
    """extrinsic.txt -> {frame: T_wc 4x4} for ``camera`` (the file holds world-to-camera matrices)."""
    out: dict[int, np.ndarray] = {}
    for parts in _table(path, 18, exact=True):  # frame cameraID + 4x4
        frame, cam = _ints(path, parts, 2)
        if cam != camera:
            continue
        try:
            T_cw = np.asarray([float(v) for v in parts[2:18]], dtype=np.float64).reshape(4, 4)
        except ValueError:
            raise DatasetError(f"{path}: non-numeric value for frame {frame}") from None
        out[frame] = np.linalg.inv(T_cw)
    return out


def read_intrinsics(path: Path, camera: int) -> tuple[float, float, float, float]:
    for parts in _table(path, 6):
        if _ints(path, parts, 2)[1] == camera:
            try:
                fx, fy, cx, cy = (float(v) for v in parts[2:6])
            except ValueError:
                raise DatasetError(f"{path}: non-numeric intrinsics {parts[2:6]}") from None
            return fx, fy, cx, cy
    raise DatasetError(f"{path}: no intrinsics for camera {camera}")


def read_moving(path: Path, camera: int) -> dict[int, set[int]]:
    """bbox.txt -> {frame: {trackID, ...} flagged isMoving}."""
    out: dict[int, set[int]] = {}
    for parts in _table(path, 11):
        frame, cam, track = _ints(path, parts, 3)
        if cam == camera and parts[10] == "True":
            out.setdefault(frame, set()).add(track)
    return out


def read_palette_png(path: Path) -> np.ndarray:
    """Palette indices (not colours) of an indexed PNG; grey/16-bit PNGs as stored."""
    from PIL import Image

    if not path.is_file():
        raise DatasetError(f"{path}: file missing")
    try:
        with Image.open(path) as im:
            if im.mode in ("P", "L", "I", "I;16"):
                return np.array(im).astype(np.int64)
            mode = im.mode
    except OSError as exc:
        raise DatasetError(f"{path}: unreadable or corrupt image ({exc})") from None
    raise DatasetError(f"{path}: expected an indexed or single-channel instance PNG, got mode {mode}")


class Vkitti2Reader(BaseReader):
    def __init__(self, options: Vkitti2Config):
        super().__init__(options)
        self.cfg = options
        self.root = Path(options.path).expanduser()
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: VKITTI2 root not found")
        self.rel = Path(options.scene) / options.variation
        cam = f"Camera_{options.camera}"
        rgb_dir = self._locate(self.rel / "frames" / "rgb" / cam)
        if rgb_dir is None:
            raise DatasetError(
                f"{self.root}: no {self.rel / 'frames' / 'rgb' / cam} (scene={options.scene!r}, "
                f"variation={options.variation!r})"
            )
        self.rgb_dir = rgb_dir
        self.depth_dir = self._locate(self.rel / "frames" / "depth" / cam)
        self.class_dir = self._locate(self.rel / "frames" / "classSegmentation" / cam)
        self.inst_dir = self._locate(self.rel / "frames" / "instanceSegmentation" / cam)
        text = self._locate(self.rel / "extrinsic.txt") or self._locate(self.rel / "intrinsic.txt")
        self.text_dir = text.parent if text is not None else rgb_dir.parents[2]

        self.T_wc: Optional[dict[int, np.ndarray]] = None
        ext = self.text_dir / "extrinsic.txt"
        if ext.is_file():
            self.T_wc = read_extrinsics(ext, options.camera)
            self.frames = sorted(self.T_wc)
            listed_in = str(ext)
        else:
            self.frames = sorted(int(p.stem.split("_")[-1]) for p in rgb_dir.glob("rgb_*.jpg"))
            listed_in = ""
        if not self.frames:
            raise DatasetError(f"{rgb_dir}: no frames")
        for f in self.frames:
            p = self._rgb(f)
            if not p.is_file():
                raise DatasetError(f"{p}: frame missing" + (f" (listed in {listed_in})" if listed_in else ""))

        w, h = image_size(self._rgb(self.frames[0]))
        intr_path = self.text_dir / "intrinsic.txt"
        if not intr_path.is_file():
            raise DatasetError(f"{intr_path}: intrinsics file not found")
        fx, fy, cx, cy = read_intrinsics(intr_path, options.camera)
        try:
            self._intr = Intrinsics(fx, fy, cx, cy, w, h)
        except ValueError as exc:
            raise DatasetError(f"{intr_path}: {exc}") from exc

        colors = self.text_dir / "colors.txt"
        self.cats: list[Category] = read_colors(colors) if colors.is_file() else []
        self._lut = {c.color[0] * 65536 + c.color[1] * 256 + c.color[2]: c for c in self.cats}
        bbox = self.text_dir / "bbox.txt"
        self.moving = read_moving(bbox, options.camera) if bbox.is_file() else None

    # ---- paths
    def _locate(self, rel: Path) -> Optional[Path]:
        cands = [self.root / rel] + [d / rel for d in sorted(self.root.iterdir()) if d.is_dir()]
        for c in cands:
            if c.exists():
                return c
        return None

    def _rgb(self, f: int) -> Path:
        return self.rgb_dir / f"rgb_{f:05d}.jpg"

    # ---- BaseReader
    def _raw_count(self) -> int:
        return len(self.frames)

    def _raw_intrinsics(self) -> Intrinsics:
        return self._intr

    def _sequence_name(self) -> str:
        return f"vkitti2_{self.cfg.scene}_{self.cfg.variation}_cam{self.cfg.camera}"

    def _source(self) -> str:
        return str(self.root / self.rel)

    def _categories(self) -> list[Category]:
        return list(self.cats)

    def _has_gt(self) -> tuple[bool, bool, bool]:
        return (self.T_wc is not None, self.depth_dir is not None, self.class_dir is not None and bool(self.cats))

    def _panoptic(self, f: int) -> tuple[PanopticSegmentation, Optional[torch.Tensor]]:
        assert self.class_dir is not None
        cpath = self.class_dir / f"classgt_{f:05d}.png"
        bgr = read_raw(cpath)
        if bgr.ndim != 3 or bgr.shape[2] < 3:
            raise DatasetError(f"{cpath}: expected an RGB class-colour PNG")
        key = bgr[..., 2].astype(np.int64) * 65536 + bgr[..., 1].astype(np.int64) * 256 + bgr[..., 0]
        cat = np.zeros(key.shape, dtype=np.int64)
        for k, c in self._lut.items():
            cat[key == k] = c.id
        inst = None
        if self.inst_dir is not None:
            ipath = self.inst_dir / f"instancegt_{f:05d}.png"
            inst = read_palette_png(ipath)
            if inst.shape != cat.shape:
                raise DatasetError(f"{ipath}: size {inst.shape[::-1]} differs from {cpath} {cat.shape[::-1]}")
        thing = np.zeros(cat.shape, dtype=bool)
        for c in self.cats:
            if c.isthing:
                thing |= cat == c.id
        ids = cat * 1000
        if inst is not None:
            ids = np.where(thing, np.where(inst > 0, ids + inst, 0), ids)
        else:
            ids[thing] = 0
        segs = []
        by_id = {c.id: c for c in self.cats}
        for sid in np.unique(ids).tolist():
            if sid == 0:
                continue
            c = by_id[sid // 1000]
            segs.append(Segment(id=int(sid), category_id=c.id, isthing=c.isthing))
        dyn = None
        if self.moving is not None and inst is not None:
            moving = self.moving.get(f, set())
            dyn_np = thing & (inst > 0) & np.isin(inst - 1, list(moving))
            dyn = torch.from_numpy(dyn_np)
        return PanopticSegmentation(ids=torch.from_numpy(ids), segments=segs), dyn

    def _load(self, raw_index: int) -> Frame:
        f = self.frames[raw_index]
        path = self._rgb(f)
        pose = None
        if self.T_wc is not None:
            from pvslam_core.outputs.trajectory_io import matrix_to_pose

            pose = torch.from_numpy(matrix_to_pose(self.T_wc[f]))
        depth = None
        if self.depth_dir is not None:
            depth = read_depth_png(self.depth_dir / f"depth_{f:05d}.png", 100.0, invalid=DEPTH_INVALID)
        pan, dyn = (None, None)
        if self.class_dir is not None and self.cats:
            pan, dyn = self._panoptic(f)
        return Frame(
            index=raw_index,
            timestamp=f / self.cfg.fps,
            image=read_rgb(path),
            intrinsics=self._intr,
            gt_pose=pose,
            gt_depth=depth,
            gt_panoptic=pan,
            gt_dynamic=dyn,
            name=path.name,
        )


def make_reader(config: Vkitti2Config, context=None) -> Vkitti2Reader:  # type: ignore[no-untyped-def]
    return Vkitti2Reader(config)
