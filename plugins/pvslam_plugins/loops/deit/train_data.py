"""Training data for the place-recognition DeiT: synthetic sequences, ground-truth place labels, batches, augmentation.

A :class:`PlaceSequence` is one generated sequence (``pvslam synth``; one world per scenario and seed) held in memory
as uint8 frames already resized to the model input (``preprocess``'s resize, so training sees what the detector
sees), with its ground-truth camera centres and optical axes.  Pairs of frames are labelled from the poses, with
the radius and angle of the sequence's own ``loops.json`` (3 m outdoors, 0.75 m indoors; optical axes within 20
degrees):

* positive: centres within ``radius`` and axes within ``max_angle`` (a revisit, or a temporal neighbour);
* negative: centres farther apart than ``neg_factor * radius``, or axes more than ``neg_angle`` apart (the same
  spot seen the other way);
* anything between is ignored (partly overlapping views: neither the same place nor clearly another).

Hard negatives: for every frame, the negatives that look most like it to the classical global descriptor
(thumbnail + gradient histograms), computed once.  The driving block is nearly point-symmetric and its facades
repeat, so these are the look-alike places a loop detector must reject.

A batch (:meth:`PlaceSequence.sample`) is drawn from one sequence: ``anchors`` random frames, one positive for each
(a revisit from another pass when there is one, with probability ``revisit_prob``), and ``hard`` hard negatives of
random anchors.  All other pairs in the batch are then same-world pairs, labelled by the same rule.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from .preprocess import full_frame_size, preprocess

NEG_FACTOR = 3.0


def quat_to_axis(q: np.ndarray) -> np.ndarray:
    """Optical axes (camera +z in the world) ``[N, 3]`` of T_wc quaternions ``[N, 4]`` (x, y, z, w)."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=1)


@dataclass
class PairLabels:
    pos: torch.Tensor  # bool [N, N]
    neg: torch.Tensor  # bool [N, N]


def pair_labels(centres: torch.Tensor, axes: torch.Tensor, radius: float, max_angle_deg: float,
                neg_factor: float = NEG_FACTOR, neg_angle_deg: float = 60.0) -> PairLabels:
    """Positive / negative masks of all frame pairs from centres ``[N, 3]`` and unit axes ``[N, 3]``."""
    d = torch.cdist(centres.double(), centres.double())
    cos = (axes.double() @ axes.double().T).clamp(-1, 1)
    pos = (d <= radius) & (cos >= math.cos(math.radians(max_angle_deg)))
    neg = (d > neg_factor * radius) | (cos < math.cos(math.radians(neg_angle_deg)))
    return PairLabels(pos, neg & ~pos)


class PlaceSequence:
    """One synthetic sequence in memory (see the module docstring)."""

    def __init__(self, root: Path, input_size, hard_k: int = 8, neg_factor: float = NEG_FACTOR,
                 neg_angle_deg: float = 60.0, cache_dir: Optional[Path] = None) -> None:
        self.root = Path(root)
        meta = json.loads((self.root / "meta.json").read_text())
        loops = json.loads((self.root / "loops.json").read_text())
        self.scenario, self.seed = str(meta["scenario"]), int(meta["seed"])
        self.radius, self.max_angle = float(loops["radius_m"]), float(loops["max_angle_deg"])
        self.min_gap = int(loops.get("min_gap", 50))
        self.gt_pairs = np.asarray(loops["pairs"], dtype=np.int64).reshape(-1, 2)
        gt = np.loadtxt(self.root / "groundtruth.txt", comments="#")
        self.timestamps = torch.from_numpy(gt[:, 0].copy())
        self.centres = torch.from_numpy(gt[:, 1:4].copy())
        self.axes = torch.from_numpy(quat_to_axis(gt[:, 4:8]))
        self.height, self.width = int(meta["height"]), int(meta["width"])
        self.input_hw = full_frame_size(self.height, self.width, input_size)
        cached = Path(cache_dir) / f"{self.root.name}-{self.input_hw[0]}x{self.input_hw[1]}.pt" if cache_dir else None
        if cached is not None and cached.is_file():
            data = torch.load(str(cached), weights_only=True)
            self.frames, self.teacher = data["frames"], data["teacher"]
        else:
            self.frames, self.teacher = self._read(len(gt))
            if cached is not None:  # written atomically: runs in parallel may share the cache
                cached.parent.mkdir(parents=True, exist_ok=True)
                tmp = cached.with_name(f".{cached.name}.{os.getpid()}.tmp")
                torch.save({"frames": self.frames, "teacher": self.teacher}, str(tmp))
                os.replace(tmp, cached)
        self.labels = pair_labels(self.centres, self.axes, self.radius, self.max_angle, neg_factor, neg_angle_deg)
        n = len(self)
        # positives from another pass (a revisit, not a temporal neighbour), for the "revisit" draws
        far_in_time = (torch.arange(n)[:, None] - torch.arange(n)[None, :]).abs() >= self.min_gap
        self._revisit = [torch.nonzero(self.labels.pos[i] & far_in_time[i]).flatten() for i in range(n)]
        self._pos = [torch.nonzero(self.labels.pos[i]).flatten() for i in range(n)]
        for i in range(n):  # a frame is always its own positive; drop it unless it is the only one
            if len(self._pos[i]) > 1:
                self._pos[i] = self._pos[i][self._pos[i] != i]
        sims = self.teacher @ self.teacher.T
        sims = torch.where(self.labels.neg, sims, torch.full_like(sims, -2.0))
        k = min(hard_k, n)
        top, idx = sims.topk(k, dim=1)
        self.hard = [idx[i][top[i] > -2.0] for i in range(n)]  # [<= k] per frame, most similar first

    def _read(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """uint8 frames ``[N, 3, h, w]`` at the model input size and classical descriptors ``[N, Dt]``."""
        from ..classical.descriptor import global_descriptor  # the teacher / hard-negative miner (no weights)

        names = [ln.split()[1] for ln in (self.root / "rgb.txt").read_text().splitlines()
                 if ln.strip() and not ln.startswith("#")]
        if len(names) != n:
            raise ValueError(f"{self.root}: {len(names)} images in rgb.txt but {n} poses in groundtruth.txt")
        frames, teacher = [], []
        for name in names:
            bgr = cv2.imread(str(self.root / name), cv2.IMREAD_COLOR)
            if bgr is None:
                raise FileNotFoundError(f"{self.root / name}: cannot read")
            rgb = np.ascontiguousarray(bgr[..., ::-1])
            teacher.append(global_descriptor(rgb))
            frames.append(torch.from_numpy(rgb).permute(2, 0, 1))
        full = torch.stack(frames)  # uint8 [N, 3, H, W]
        x = torch.cat([preprocess(full[i : i + 64], self.input_hw, "full_frame", mean=(0, 0, 0), std=(1, 1, 1))
                       for i in range(0, len(full), 64)])
        frames_small = (x * 255.0).round().clamp(0, 255).to(torch.uint8)  # what the detector's resize gives
        return frames_small, torch.from_numpy(np.stack(teacher)).float()

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    @property
    def name(self) -> str:
        return f"{self.scenario}/seed{self.seed}"

    def sample(self, gen: torch.Generator, anchors: int, hard: int, revisit_prob: float = 0.5) -> torch.Tensor:
        """Frame indices ``[B]`` of one batch (anchors, their positives, hard negatives; may repeat frames)."""
        n = len(self)
        a = torch.randint(0, n, (anchors,), generator=gen)
        pos = []
        for i in a.tolist():
            rev = self._revisit[i]
            pool = rev if len(rev) and float(torch.rand((), generator=gen)) < revisit_prob else self._pos[i]
            pos.append(int(pool[int(torch.randint(0, len(pool), (), generator=gen))]))
        neg = []
        for i in a[torch.randint(0, anchors, (hard,), generator=gen)].tolist():
            pool = self.hard[i]
            if len(pool):
                neg.append(int(pool[int(torch.randint(0, len(pool), (), generator=gen))]))
        return torch.cat([a, torch.tensor(pos, dtype=torch.long), torch.tensor(neg, dtype=torch.long)])


def load_sequences(roots: Sequence[Path], input_size, hard_k: int = 8, cache_dir: Optional[Path] = None,
                   neg_factor: float = NEG_FACTOR, neg_angle_deg: float = 60.0) -> list[PlaceSequence]:
    return [PlaceSequence(r, input_size, hard_k, neg_factor, neg_angle_deg, cache_dir) for r in roots]


# ------------------------------------------------------------------------------------------- augmentation --
@dataclass
class Augment:
    """Photometric and small geometric jitter of uint8 frames ``[B, 3, h, w]`` -> float ``[B, 3, h, w]`` in [0, 1].

    Exposure (gain, gamma, per-channel colour), Gaussian noise, and a random crop of ``crop_min``..1 of each side
    resampled back to the full size (a small zoom + shift, bilinear through one batched ``grid_sample``).  No
    flips: a mirrored street is not the same place.
    """

    gain: tuple[float, float] = (0.6, 1.4)
    gamma: tuple[float, float] = (0.7, 1.4)
    colour: float = 0.08
    noise: float = 0.03
    crop_min: float = 0.8

    def __call__(self, x: torch.Tensor, gen: Optional[torch.Generator] = None) -> torch.Tensor:
        B = x.shape[0]
        u = lambda *s: torch.rand(*s, generator=gen)  # noqa: E731
        x = x.float() / 255.0
        # geometry: per-sample scale s in [crop_min, 1] (shared by both axes, so the aspect stays) and a shift
        # keeping the crop inside the image
        s = self.crop_min + (1 - self.crop_min) * u(B)
        tx, ty = (1 - s) * (2 * u(B) - 1), (1 - s) * (2 * u(B) - 1)
        theta = torch.zeros(B, 2, 3)
        theta[:, 0, 0], theta[:, 1, 1], theta[:, 0, 2], theta[:, 1, 2] = s, s, tx, ty
        grid = F.affine_grid(theta, list(x.shape), align_corners=False)
        x = F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)
        # exposure: gamma, gain, colour balance
        lo, hi = self.gamma
        gamma = torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u(B))[:, None, None, None]
        gain = (self.gain[0] + (self.gain[1] - self.gain[0]) * u(B))[:, None, None, None]
        colour = 1 + self.colour * (2 * u(B, 3) - 1)[:, :, None, None]
        x = x.clamp_min(0).pow(gamma) * gain * colour
        x = x + self.noise * u(B)[:, None, None, None] * torch.randn(x.shape, generator=gen)
        return x.clamp(0, 1)
