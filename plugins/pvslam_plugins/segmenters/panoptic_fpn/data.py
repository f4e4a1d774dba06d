"""Training data for the reduced PanopticFPN: frames of the built-in synthetic scenarios with exact panoptic labels,
augmentations, and the conversion of a panoptic id map into the network's targets.

Frames are rendered straight from the generator's scenes (``scenarios.build`` + ``render``: the same pixels and
ids ``pvslam synth`` writes) at ``frames_per_sequence`` evenly spaced positions of each scenario's default-length
trajectory (so a sample covers the whole route, not only its first seconds), and cached as one ``.npz`` per
(scenario, seed): a resumed or repeated training run does not render again.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from pvslam_core.outputs._atomic import atomic_open
from pvslam_core.types import Segment

from .categories import CategorySet
from .losses import IGNORE, InstanceTargets

__all__ = ["Sample", "synthetic_category_set", "render_samples", "load_samples", "panoptic_targets",
           "Augment", "SYNTHETIC_MOVABLE"]

#: categories of the synthetic generator that move in its scenes (parked cars are cars too: movable, not moving)
SYNTHETIC_MOVABLE = ("car", "truck")


@dataclass
class Sample:
    """One labelled frame: RGB ``uint8 [3, H, W]``, panoptic ids ``int32 [H, W]`` (0 = void) and their segments.
    A training run holds every frame in memory: int32 ids take half of int64's (the generator's ids are below 2^24,
    exact in the augmentation's float32 too)."""

    image: torch.Tensor
    ids: torch.Tensor
    segments: list[Segment]
    name: str = ""


def synthetic_category_set() -> CategorySet:
    """The generator's 13 categories (10 stuff, 3 things) as a :class:`CategorySet`, car/truck movable."""
    from pvslam_plugins.datasets.synthetic.scene import CATEGORIES

    return CategorySet.from_categories("synthetic", CATEGORIES, SYNTHETIC_MOVABLE)


def _segments_of(ids: np.ndarray, thing_cats: set[int]) -> list[Segment]:
    # the generator's id convention: category_id * 1000 + instance (writer.segments_info)
    return [Segment(int(s), int(s) // 1000, (int(s) // 1000) in thing_cats) for s in np.unique(ids) if s != 0]


def render_samples(scenario: str, seed: int, frames: int, width: int = 320, height: int = 240,
                   domain: Optional[str] = None) -> list[Sample]:
    """Render ``frames`` evenly spaced frames of ``scenario`` (default length) with ``seed``; ``domain``: the
    generator's domain randomisation split (None = the plain generator)."""
    from pvslam_plugins.datasets.synthetic.render import render
    from pvslam_plugins.datasets.synthetic.scenarios import build
    from pvslam_plugins.datasets.synthetic.scene import CATEGORIES

    sc = build(scenario, width=width, height=height, seed=seed, domain=domain)
    things = {c.id for c in CATEGORIES if c.isthing}
    n = sc.num_frames
    # a seed-dependent offset so that different seeds do not all sample the same trajectory positions
    step = n / frames
    offset = (seed * 0.618034 % 1.0) * step
    idx = sorted({min(n - 1, int(offset + k * step)) for k in range(frames)})
    out = []
    tag = f"/{domain}" if domain else ""
    for i in idx:
        r = render(sc.scene, i, sc.poses[i], sc.camera)
        ids = np.asarray(r.panoptic, np.int32)
        out.append(Sample(torch.from_numpy(np.ascontiguousarray(r.rgb.transpose(2, 0, 1))), torch.from_numpy(ids),
                          _segments_of(ids, things), f"{scenario}/seed{seed}/{i:06d}{tag}"))
    return out


def load_samples(cache_dir: Path, scenario: str, seed: int, frames: int, width: int = 320,
                 height: int = 240, domain: Optional[str] = None) -> list[Sample]:
    """:func:`render_samples` through an ``.npz`` cache in ``cache_dir``."""
    from pvslam_plugins.datasets.synthetic.scene import CATEGORIES

    style = f"-{domain}" if domain else ""
    path = Path(cache_dir) / f"{scenario}-seed{seed}-n{frames}-{width}x{height}{style}.npz"
    things = {c.id for c in CATEGORIES if c.isthing}
    if path.is_file():
        z = np.load(path)
        names = json.loads(str(z["names"]))
        return [Sample(torch.from_numpy(img), torch.from_numpy(ids.astype(np.int32, copy=False)),
                       _segments_of(ids, things), name) for img, ids, name in zip(z["images"], z["ids"], names)]
    samples = render_samples(scenario, seed, frames, width, height, domain)
    # a temporary file of this process's own: two trainings may share a cache and render the same sequence
    with atomic_open(path, "wb") as f:
        np.savez_compressed(f, images=np.stack([s.image.numpy() for s in samples]),
                            ids=np.stack([s.ids.numpy().astype(np.int32) for s in samples]),
                            names=json.dumps([s.name for s in samples]))
    return samples


# ------------------------------------------------------------------------------------------------------ targets
def panoptic_targets(ids: torch.Tensor, segments: Sequence[Segment], cats: CategorySet,
                     min_area: int = 1) -> tuple[torch.Tensor, InstanceTargets]:
    """Panoptic ids ``int64 [H, W]`` -> semantic labels ``int64 [H, W]`` (channel of each stuff category, 0 for
    things, :data:`IGNORE` for void and unknown ids) and the thing instances (tight boxes, contiguous classes,
    masks).  Instances smaller than ``min_area`` pixels keep semantic label 0 but are not targets."""
    h, w = ids.shape
    sem_of_cat = {int(c): k for k, c in enumerate(cats.semantic_ids().tolist()) if k > 0}
    cls_of_cat = {int(c): k for k, c in enumerate(cats.thing_ids().tolist())}
    uniq, inv = torch.unique(ids, return_inverse=True)
    seg_by_id = {s.id: s for s in segments}
    lut = torch.full((uniq.numel(),), IGNORE, dtype=torch.int64)
    thing_rows, thing_cls = [], []
    for k, sid in enumerate(uniq.tolist()):
        s = seg_by_id.get(sid)
        if sid == 0 or s is None:
            continue
        if s.isthing and s.category_id in cls_of_cat:
            lut[k] = 0
            thing_rows.append(k)
            thing_cls.append(cls_of_cat[s.category_id])
        elif not s.isthing and s.category_id in sem_of_cat:
            lut[k] = sem_of_cat[s.category_id]
    sem = lut[inv]
    if thing_rows:
        masks = inv[None] == torch.tensor(thing_rows)[:, None, None]  # [G, H, W]
        area = masks.flatten(1).sum(1)
        keep = area >= max(min_area, 1)
        masks, classes = masks[keep], torch.tensor(thing_cls)[keep]
    else:
        masks, classes = torch.zeros((0, h, w), dtype=torch.bool), torch.zeros(0, dtype=torch.int64)
    return sem, InstanceTargets(_tight_boxes(masks), classes, masks)


def _tight_boxes(masks: torch.Tensor) -> torch.Tensor:
    """``[G, 4]`` float boxes ``[x0, y0, x1 + 1, y1 + 1]`` enclosing each non-empty mask ``[G, H, W]``."""
    if masks.shape[0] == 0:
        return torch.zeros((0, 4))
    rows, cols = masks.any(dim=2), masks.any(dim=1)  # [G, H], [G, W]
    h, w = masks.shape[1:]
    ar_h, ar_w = torch.arange(h), torch.arange(w)
    y0 = torch.where(rows, ar_h, h).min(dim=1).values
    y1 = torch.where(rows, ar_h, -1).max(dim=1).values + 1
    x0 = torch.where(cols, ar_w, w).min(dim=1).values
    x1 = torch.where(cols, ar_w, -1).max(dim=1).values + 1
    return torch.stack((x0, y0, x1, y1), dim=1).float()


# ------------------------------------------------------------------------------------------------ augmentation
@dataclass
class Augment:
    """Random scale (bilinear image, nearest ids), horizontal flip, crop, and photometric jitter."""

    scale: tuple[float, float] = (0.75, 1.25)
    crop: Optional[tuple[int, int]] = (192, 256)  # (h, w); None = whole image
    flip: bool = True
    brightness: float = 0.25  # multiplicative factor drawn in [1 - b, 1 + b]
    contrast: float = 0.25
    saturation: float = 0.25
    noise: float = 3.0  # std of additive Gaussian noise on 0..255 pixels

    def __call__(self, image: torch.Tensor, ids: torch.Tensor, gen: torch.Generator
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """``uint8 [3, H, W]``, integer ids ``[H, W]`` -> float ``[3, h, w]`` on 0..255 and ``int64 [h, w]``."""
        def uniform(lo: float, hi: float) -> float:
            return lo + (hi - lo) * float(torch.rand((), generator=gen))

        x = image.float()[None]
        lab = ids[None, None].float()
        s = uniform(*self.scale)
        h, w = image.shape[1:]
        nh, nw = max(8, int(round(h * s))), max(8, int(round(w * s)))
        if (nh, nw) != (h, w):
            x = F.interpolate(x, size=(nh, nw), mode="bilinear", align_corners=False, antialias=s < 1)
            lab = F.interpolate(lab, size=(nh, nw), mode="nearest")
        if self.flip and float(torch.rand((), generator=gen)) < 0.5:
            x, lab = x.flip(-1), lab.flip(-1)
        if self.crop is not None:
            ch, cw = min(self.crop[0], nh), min(self.crop[1], nw)
            y0 = int(torch.randint(0, nh - ch + 1, (), generator=gen))
            x0 = int(torch.randint(0, nw - cw + 1, (), generator=gen))
            x, lab = x[..., y0:y0 + ch, x0:x0 + cw], lab[..., y0:y0 + ch, x0:x0 + cw]
        x = x[0]
        grey = (0.299 * x[0] + 0.587 * x[1] + 0.114 * x[2])[None]
        x = grey + (x - grey) * uniform(1 - self.saturation, 1 + self.saturation)  # saturation
        x = grey.mean() + (x - grey.mean()) * uniform(1 - self.contrast, 1 + self.contrast)
        x = x * uniform(1 - self.brightness, 1 + self.brightness)
        if self.noise > 0:
            x = x + self.noise * torch.randn(x.shape, generator=gen)
        return x.clamp(0, 255), lab[0, 0].round().to(torch.int64)
