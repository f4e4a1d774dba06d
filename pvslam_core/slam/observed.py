"""Which pixels of a keyframe's depth have been measured, and how much they count before they are.

A new keyframe's inverse depth starts as the previous keyframe's moved into it (:mod:`.new_keyframe`); the pixels
nothing lands on are *filled* (:func:`~pvslam_core.geometry.projective.fill_holes`), a guess.  Only an edge with
parallax (translation-induced flow) measures a pixel's depth; through a fast pan or a turn on the spot there is
none, so a run of keyframes can be mostly filled guesses, and a pose fitted to those guesses turns with them.

:class:`ObservedMasks` keeps one bool map ``[h, w]`` per keyframe id (BA resolution): ``True`` = measured.  A warped
keyframe inherits the flag of the pixels that land on it; after each window BA a pixel of an edge's source keyframe
becomes measured when that edge moves it by at least ``parallax`` BA px of translation-only flow (current estimate;
a pixel farther than the keyframe's median depth counts at the median) with a confidence above ``min_weight``.
Keyframes of a fresh two-view initialisation are measured everywhere (their depth is the triangulation's).  Two
uses, each off at 1:

* the window BA (and the pose guess below when it keeps every pixel) multiplies the confidence of a source pixel
  not measured yet by ``weight`` (:data:`UNOBSERVED_WEIGHT`).  A weight, not a mask: the pixel's depth is a BA
  variable, and its update must still come from the first edge with parallax while the measured pixels hold the
  poses;
* the motion-only guess of a new keyframe's pose (depth fixed) uses the measured pixels only when they are at least
  ``guess_min`` of the confident ones (:data:`GUESS_MIN_MEASURED`; :meth:`ObservedMasks.guess_weight`).
"""
from __future__ import annotations

import torch

from ..geometry.projective import edge_transforms, pixel_grid, project_points

# confidence factor, in the window BA, of a depth pixel no edge with parallax has measured yet
# (docs/decisions.md: UNOBSERVED_WEIGHT)
UNOBSERVED_WEIGHT = 0.3
# a new keyframe's pose guess uses only its reference's measured pixels when they are at least this share of the
# tracked ones (docs/decisions.md: GUESS_MIN_MEASURED)
GUESS_MIN_MEASURED = 0.5
# translation-only flow (reference BA px, adapt.ba_px_scale) an edge must give a pixel to count its depth as measured
OBSERVED_PARALLAX = 1.0


class ObservedMasks:
    """The measured-pixel masks of the keyframes and the two confidence rules (see the module docstring)."""

    def __init__(self, weight: float, parallax: float, guess_min: float = 1.0, min_weight: float = 0.1):
        self.weight = float(weight)  # the confidence factor of a pixel not measured yet in the window BA
        self.parallax = float(parallax)
        self.guess_min = float(guess_min)
        self.min_weight = float(min_weight)
        self.masks: dict[int, torch.Tensor] = {}  # keyframe id -> bool [h, w]
        self.settled: dict[int, float] = {}  # keyframe id -> its measured share after its own window BA

    @property
    def active(self) -> bool:
        """Whether the masks change anything (else the mapper does not keep them up to date)."""
        return self.weight < 1.0 or self.guess_min < 1.0

    def guess_weight(self, kf_id: int, weight: torch.Tensor) -> torch.Tensor:
        """The confidences ``weight [2, h, w]`` of a pose guess against keyframe ``kf_id`` (depth fixed): only its
        measured pixels when they are at least ``guess_min`` of the confident ones, else all of them with the
        unmeasured ones at ``self.weight``.  Why none at all: with the depth fixed, a guessed depth's residual is
        wrong by its parallax, and a camera with a narrow field of view trades rotation for translation along an
        almost flat direction of the cost; any weight left on those pixels moves the pose along it
        (tests/slam/test_mapper.py shows it on a keyframe whose depth is guessed 3x off on half its pixels)."""
        m = self.masks.get(int(kf_id))
        if m is None:
            return weight
        m = m.to(weight.device)
        tracked = weight.mean(dim=0) > self.min_weight
        frac = float((m & tracked).sum()) / max(1, int(tracked.sum()))
        if frac >= self.guess_min:
            return weight * m
        return weight * torch.where(m, 1.0, self.weight)

    def fraction(self, kf_id: int) -> float:
        """The measured share of keyframe ``kf_id``'s pixels (1 for a keyframe with no mask on record)."""
        m = self.masks.get(int(kf_id))
        return 1.0 if m is None else float(m.float().mean())

    def settle(self, kf_id: int) -> None:
        """Record keyframe ``kf_id``'s measured share as it is now, after its own window BA (first call only): what
        its depth was when the next keyframes were placed against it (.scale_gaps)."""
        self.settled.setdefault(int(kf_id), self.fraction(kf_id))

    def settled_fraction(self, kf_id: int) -> float:
        """The share :meth:`settle` recorded, else the current one (:meth:`fraction`)."""
        got = self.settled.get(int(kf_id))
        return self.fraction(kf_id) if got is None else got

    def set(self, kf_id: int, mask: torch.Tensor) -> None:
        self.masks[int(kf_id)] = mask.bool()

    def forget(self, kf_id: int) -> None:
        self.masks.pop(int(kf_id), None)
        self.settled.pop(int(kf_id), None)

    def factor(self, kf_ids: list[int], shape: tuple[int, int], device) -> torch.Tensor:
        """Confidence factors ``[len(kf_ids), 1, h, w]`` (one per edge source): 1 where measured, ``weight``
        elsewhere (a keyframe with no mask on record counts as measured)."""
        uniq = sorted(set(int(k) for k in kf_ids))
        ones = torch.ones(shape, dtype=torch.bool, device=device)
        masks = torch.stack([self.masks.get(k, ones).to(device) for k in uniq])  # [U, h, w]
        pos = {k: n for n, k in enumerate(uniq)}
        rows = torch.tensor([pos[int(k)] for k in kf_ids], dtype=torch.long, device=device)
        return torch.where(masks, 1.0, self.weight)[rows].unsqueeze(1)

    def mark(self, poses_wc: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, ids: list[int],
             ii: torch.Tensor, jj: torch.Tensor, weight: torch.Tensor) -> None:
        """After a BA: the pixels of each edge ``ii -> jj`` (graph indices; ``ids`` their stable ids) with at least
        ``parallax`` BA px of translation-only flow (at no more than the source's median depth) and a confidence
        ``weight [E, 2, h, w]`` (mean of the two coordinates) above ``min_weight`` become measured in the source
        keyframe."""
        if ii.numel() == 0:
            return
        h, w = disps.shape[-2:]
        R, t = edge_transforms(poses_wc.double(), ii, jj)
        d = disps[ii].reshape(ii.numel(), -1).double()  # [E, P]
        # a pixel farther than the source's median depth counts at the median: its small inverse depth is measured
        # by a baseline that moves the median depth by `parallax` (else the sky and the far road never are, and the
        # pixels that hold a car camera's rotation stay down-weighted; docs/decisions.md: OBSERVED_PARALLAX)
        d = torch.maximum(d, d.median(dim=1, keepdim=True).values)
        tr = project_points(R, t, d, intr.double(), h, w, min_depth=1e-3, translation_only=True)
        grid = pixel_grid(h, w, d.device, torch.float64).reshape(1, -1, 2)
        flow = torch.hypot(tr["u"] - grid[..., 0], tr["v"] - grid[..., 1])  # [E, P]
        seen = (flow >= self.parallax) & tr["valid"] & (weight.mean(dim=1).reshape(ii.numel(), -1) > self.min_weight)
        for src in torch.unique(ii).tolist():
            kf_id = ids[src]
            m = self.masks.get(kf_id)
            if m is None:
                continue
            new = seen[ii == src].any(dim=0).reshape(h, w).to(m.device)
            self.masks[kf_id] = m | new

