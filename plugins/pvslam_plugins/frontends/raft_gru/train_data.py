"""Training clips from the built-in synthetic generator: images, exact camera-to-world poses, exact depth, dynamic
masks, intrinsics.

A *sequence* (scenario, seed) is rendered once into the cache folder at the training resolution and held in memory
as arrays; a *clip* is ``length`` frames of it at a fixed ``stride``.  Strides are chosen per clip so that the mean
ground-truth flow between consecutive frames (static pixels, 1/8 resolution) lies in ``flow_range``: DROID samples
its training frames by flow distance too, so a 30 Hz handheld room and a 10 Hz street give comparable motion.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from pvslam_core.geometry.projective import reproject
from pvslam_core.types import Intrinsics


@dataclass
class Sequence:
    """One rendered sequence in memory."""

    name: str
    images: torch.Tensor  # uint8 [T, 3, H, W] RGB
    poses: torch.Tensor  # float64 [T, 7] T_wc
    disps: torch.Tensor  # float32 [T, H, W] inverse depth, 0 = invalid (sky)
    dynamic: torch.Tensor  # bool [T, H, W] moving independently
    intrinsics: Intrinsics  # of the images


@dataclass
class Clip:
    """``N`` frames of a sequence (one training / validation sample)."""

    name: str
    frames: list[int]
    images: torch.Tensor  # uint8 [N, 3, H, W]
    poses: torch.Tensor  # float64 [N, 7] T_wc
    disps: torch.Tensor  # float32 [N, H, W]
    dynamic: torch.Tensor  # bool [N, H, W]
    intrinsics: Intrinsics


def load_sequence(cache: Path, scenario: str, seed: int, num_frames: int, width: int, height: int) -> Sequence:
    """Render (or find in ``cache``) ``scenario`` with ``seed`` and read it into memory."""
    from pvslam_plugins.datasets.synthetic.generator import generate
    from pvslam_plugins.datasets.synthetic.reader import SyntheticSequence

    root = generate(scenario, Path(cache) / f"{scenario}-s{seed}-{width}x{height}-n{num_frames}",
                    num_frames=num_frames, seed=seed, width=width, height=height, progress=False)
    seq = SyntheticSequence(root)
    imgs, depths, dyns = [], [], []
    for i in range(len(seq)):
        a = seq.arrays(i, ("depth", "dynamic"))
        imgs.append(torch.from_numpy(np.ascontiguousarray(a["rgb"].transpose(2, 0, 1))))
        depths.append(torch.from_numpy(a["depth"]))
        dyns.append(torch.from_numpy(a["dynamic"]))
    depth = torch.stack(depths)
    disp = torch.where(depth > 0, 1.0 / depth.clamp(min=1e-6), torch.zeros_like(depth))
    return Sequence(f"{scenario}/seed{seed}", torch.stack(imgs), torch.from_numpy(seq.poses).double(), disp,
                    torch.stack(dyns), seq.intrinsics)


def mean_static_flow(seq: Sequence, a: int, b: int, stride: int = 8) -> float:
    """Mean ground-truth flow magnitude ``a -> b`` over valid static pixels, in 1/``stride``-resolution px."""
    intr = seq.intrinsics.scaled(1.0 / stride)
    d = seq.disps[[a, b], stride // 2:: stride, stride // 2:: stride].double()
    h, w = d.shape[-2:]
    coords, valid = reproject(seq.poses[[a, b]], d, intr.vector(torch.float64), torch.tensor([0]), torch.tensor([1]))
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    mag = ((coords[0, ..., 0] - xs) ** 2 + (coords[0, ..., 1] - ys) ** 2).sqrt()
    ok = valid[0] & (d[0] > 0) & ~seq.dynamic[a, stride // 2:: stride, stride // 2:: stride]
    return float(mag[ok].mean()) if bool(ok.any()) else float("inf")


def sample_clip(seq: Sequence, length: int, gen: torch.Generator, flow_range: tuple[float, float] = (1.0, 6.0),
                max_stride: int = 6, tries: int = 20) -> Clip:
    """A random clip of ``length`` frames whose consecutive-frame flow lies in ``flow_range`` (else the closest of
    ``tries`` draws)."""
    T = seq.images.shape[0]
    best, best_err = None, float("inf")
    lo, hi = flow_range
    for _ in range(tries):
        stride = int(torch.randint(1, max_stride + 1, (1,), generator=gen))
        span = (length - 1) * stride
        if span >= T:
            continue
        start = int(torch.randint(0, T - span, (1,), generator=gen))
        frames = [start + k * stride for k in range(length)]
        f = mean_static_flow(seq, frames[0], frames[1])
        err = 0.0 if lo <= f <= hi else min(abs(f - lo), abs(f - hi))
        if err < best_err:
            best, best_err = frames, err
        if err == 0.0:
            break
    if best is None:
        best = list(range(min(length, T)))
    return clip_of(seq, best)


def clip_of(seq: Sequence, frames: list[int]) -> Clip:
    idx = torch.tensor(frames)
    return Clip(seq.name, list(frames), seq.images[idx], seq.poses[idx], seq.disps[idx], seq.dynamic[idx],
                seq.intrinsics)


def fixed_clips(seqs: list[Sequence], per_sequence: int, length: int, seed: int,
                flow_range: tuple[float, float] = (1.0, 6.0), max_stride: int = 6) -> list[Clip]:
    """A deterministic set of clips (validation, or the single overfitting clip)."""
    gen = torch.Generator().manual_seed(seed)
    return [sample_clip(s, length, gen, flow_range, max_stride) for s in seqs for _ in range(per_sequence)]


def edges_within(n: int, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All directed edges ``i -> j`` with ``0 < |i - j| <= radius`` among ``n`` frames."""
    ii, jj = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    keep = ((ii - jj).abs() > 0) & ((ii - jj).abs() <= radius)
    return ii[keep], jj[keep]


def check_size(width: int, height: int) -> Optional[str]:
    """Why a training size cannot work, or None (multiples of 8, >= 128 for the 4-level pyramid)."""
    if width % 8 or height % 8:
        return f"width and height must be multiples of 8, got {width}x{height}"
    if width < 128 or height < 128:
        return f"width and height must be >= 128 (4 correlation levels on the 1/8 map), got {width}x{height}"
    return None
