"""Training pairs for the fusion layer: consecutive frames ``(t-1, t)`` of the generator's scenarios with moving
vehicles, with what the VPS head gets at run time (a flow at the VO's 1/8 resolution, the previous frame's depth)
and frame ``t``'s exact panoptic labels.

The flow is OpenCV DIS between the two rendered images, reduced to 1/8 resolution like the VO's motion cue: the
layer learns from a measured, imperfect flow rather than from an exact one it would never see in a run.  The
depth is the generator's (the VO's is an estimate; it only orders writes).  Pairs are cached per (scenario, seed)
as ``.npz``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from pvslam_core.outputs._atomic import atomic_open
from pvslam_core.types import Segment

__all__ = ["Pair", "render_pairs", "load_pairs"]


@dataclass
class Pair:
    image0: torch.Tensor  # uint8 [3, H, W], frame t-1
    image1: torch.Tensor  # uint8 [3, H, W], frame t
    ids1: torch.Tensor  # int64 [H, W], panoptic labels of frame t (generator ids: category * 1000 + instance)
    segments1: list[Segment]
    flow: torch.Tensor  # float32 [2, H/8, W/8] in frame pixels: t-1 -> t
    depth0: torch.Tensor  # float32 [H/8, W/8] z-depth of frame t-1, 0 = unknown
    name: str = ""


def _segments_of(ids: np.ndarray) -> list[Segment]:
    from pvslam_plugins.datasets.synthetic.scene import CATEGORIES

    things = {c.id for c in CATEGORIES if c.isthing}
    return [Segment(int(s), int(s) // 1000, (int(s) // 1000) in things) for s in np.unique(ids) if s != 0]


def render_pairs(scenario: str, seed: int, pairs: int, width: int = 320, height: int = 240,
                 downsample: int = 8, domain: Optional[str] = None) -> list[Pair]:
    """``pairs`` evenly spaced consecutive-frame pairs of ``scenario`` (default length) with ``seed``; ``domain``:
    the generator's domain randomisation split (None = the plain generator)."""
    import cv2

    from pvslam_plugins.datasets.synthetic.render import render
    from pvslam_plugins.datasets.synthetic.scenarios import build
    from pvslam_plugins.vps.warp_iou.warp import dis_flow

    sc = build(scenario, width=width, height=height, seed=seed, domain=domain)
    n = sc.num_frames
    step = (n - 1) / pairs
    idx = sorted({1 + int(k * step + (seed * 0.618034 % 1.0) * step) for k in range(pairs)} - {n})
    hs, ws = height // downsample, width // downsample
    out = []
    for i in idx:
        r0 = render(sc.scene, i - 1, sc.poses[i - 1], sc.camera)
        r1 = render(sc.scene, i, sc.poses[i], sc.camera)
        im0 = torch.from_numpy(np.ascontiguousarray(r0.rgb.transpose(2, 0, 1)))
        im1 = torch.from_numpy(np.ascontiguousarray(r1.rgb.transpose(2, 0, 1)))
        f = dis_flow(im0, im1, "medium", max(width, height))  # [2, H, W] frame pixels
        f = cv2.resize(np.ascontiguousarray(f.transpose(1, 2, 0)), (ws, hs), interpolation=cv2.INTER_AREA)
        d = np.asarray(r0.depth, np.float32)[downsample // 2::downsample, downsample // 2::downsample][:hs, :ws]
        ids = np.asarray(r1.panoptic, np.int64)
        out.append(Pair(im0, im1, torch.from_numpy(ids), _segments_of(ids),
                        torch.from_numpy(np.ascontiguousarray(f.transpose(2, 0, 1))), torch.from_numpy(d.copy()),
                        f"{scenario}/seed{seed}/{i:06d}" + (f"/{domain}" if domain else "")))
    return out


def load_pairs(cache_dir: Path, scenario: str, seed: int, pairs: int, width: int = 320, height: int = 240,
               domain: Optional[str] = None) -> list[Pair]:
    """:func:`render_pairs` through an ``.npz`` cache in ``cache_dir``."""
    look = f"-{domain}" if domain else ""
    path = Path(cache_dir) / f"pairs-{scenario}-seed{seed}{look}-n{pairs}-{width}x{height}.npz"
    if path.is_file():
        z = np.load(path)
        names = json.loads(str(z["names"]))
        return [Pair(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(i.astype(np.int64)),
                     _segments_of(i), torch.from_numpy(f), torch.from_numpy(d), nm)
                for a, b, i, f, d, nm in zip(z["image0"], z["image1"], z["ids1"], z["flow"], z["depth0"], names)]
    out = render_pairs(scenario, seed, pairs, width, height, domain=domain)
    # a temporary file of this process's own: two trainings may share a cache and render the same sequence
    with atomic_open(path, "wb") as f:
        np.savez_compressed(f, image0=np.stack([p.image0.numpy() for p in out]),
                            image1=np.stack([p.image1.numpy() for p in out]),
                            ids1=np.stack([p.ids1.numpy().astype(np.int32) for p in out]),
                            flow=np.stack([p.flow.numpy() for p in out]),
                            depth0=np.stack([p.depth0.numpy() for p in out]),
                            names=json.dumps([p.name for p in out]))
    return out
