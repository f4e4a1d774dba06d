"""PCA / whitening of global descriptors (the ``PCA`` of the paper's eq. 12), fixed or fitted online.

Why: raw DeiT class tokens of any two images have a large common component (cosine similarities of unrelated
images are high and bunched together), so the cosine of eq. 8 separates places poorly.  Removing the mean and
(optionally) equalising the variance of the principal directions spreads the scores out.

* :class:`PCAWhitening` is a fitted transform ``y = s * (U^T (x - mean))`` with ``U`` the top principal axes and
  ``s = 1 / sqrt(eigenvalue + shrinkage * mean_eigenvalue)`` when whitening (``s = 1`` otherwise).  With
  ``shrinkage = 0`` the transformed fit set has identity covariance (population covariance, divided by N).
  Shrinkage keeps low-variance directions, which are mostly noise when few samples were seen, from being
  blown up.
* :class:`OnlinePCA` keeps float64 running moments (``n``, ``sum x``, ``sum x x^T``) of every descriptor seen so
  far and refits a :class:`PCAWhitening` on a geometric schedule (see its docstring).  Removing a keyframe does
  not remove it from the statistics: it was still a view of the environment.

Both expose ``transform(x [..., D]) -> [..., d]`` and ``version`` (changes whenever the transform changes), so a
descriptor store can re-project its raw descriptors lazily.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import torch

#: eigenvalues below this fraction of the largest count as zero (the null space of a rank-deficient fit)
_RANK_TOL = 1e-9


class PCAWhitening:
    """A fitted PCA (optionally whitening) transform.

    ``mean [D]``, ``components [d, D]`` (rows = principal axes, by decreasing variance, sign fixed so that the
    largest-magnitude entry of each row is positive), ``eigenvalues [d]`` (population variances along the axes).
    """

    version = 0  # a fixed transform never changes

    def __init__(self, mean: torch.Tensor, components: torch.Tensor, eigenvalues: torch.Tensor,
                 whiten: bool = True, shrinkage: float = 0.0, num_samples: int = 0) -> None:
        D = mean.shape[-1]
        if mean.dim() != 1 or components.dim() != 2 or components.shape[1] != D or eigenvalues.shape != (
                components.shape[0],):
            raise ValueError(f"PCA shapes do not agree: mean {tuple(mean.shape)}, components "
                             f"{tuple(components.shape)}, eigenvalues {tuple(eigenvalues.shape)}")
        # stored as float32; the projection is derived from the stored values, so a saved and reloaded
        # transform is bitwise the same
        self.mean = mean.float()
        self.components = components.float()
        self.eigenvalues = eigenvalues.float()
        components, eigenvalues = self.components, self.eigenvalues
        self.whiten = bool(whiten)
        self.shrinkage = float(shrinkage)
        self.num_samples = int(num_samples)
        if self.whiten:
            reg = self.shrinkage * float(eigenvalues.double().mean()) if len(eigenvalues) else 0.0
            scale = (eigenvalues.double().clamp_min(0) + reg).rsqrt()
        else:
            scale = torch.ones_like(eigenvalues, dtype=torch.float64)
        # fold the scale into the projection: one matmul per transform
        self._proj = (components.double() * scale[:, None]).float().T.contiguous()  # [D, d]

    @property
    def in_dim(self) -> int:
        return int(self.mean.shape[0])

    @property
    def out_dim(self) -> int:
        return int(self.components.shape[0])

    # --- fitting ---------------------------------------------------------------------------------------------
    @classmethod
    def fit(cls, x: torch.Tensor, dim: Optional[int] = None, whiten: bool = True,
            shrinkage: float = 0.0) -> "PCAWhitening":
        """Fit on ``x [N, D]`` (float64 internally)."""
        if x.dim() != 2 or x.shape[0] < 2:
            raise ValueError(f"PCA fit needs x [N >= 2, D], got {tuple(x.shape)}")
        x = x.double()
        return cls.from_moments(x.shape[0], x.sum(0), x.T @ x, dim, whiten, shrinkage)

    @classmethod
    def from_moments(cls, n: int, s1: torch.Tensor, s2: torch.Tensor, dim: Optional[int] = None,
                     whiten: bool = True, shrinkage: float = 0.0) -> "PCAWhitening":
        """Fit from ``n``, ``s1 = sum x [D]`` and ``s2 = sum x x^T [D, D]``.

        The output dimension is ``min(dim, rank)``: with N samples the covariance has rank <= N - 1, and
        directions of zero variance carry no information (and cannot be whitened).
        """
        if n < 2:
            raise ValueError(f"PCA fit needs at least 2 samples, got {n}")
        mean = s1.double() / n
        cov = s2.double() / n - torch.outer(mean, mean)
        cov = 0.5 * (cov + cov.T)
        evals, evecs = torch.linalg.eigh(cov)  # ascending
        evals, evecs = evals.flip(0), evecs.flip(1)
        rank = int((evals > _RANK_TOL * max(float(evals[0]), 1e-30)).sum())
        d = max(1, min(rank, dim if dim is not None else rank))
        comps = evecs[:, :d].T  # [d, D]
        # deterministic signs (eigh's are arbitrary): largest-magnitude entry positive
        idx = comps.abs().argmax(1)
        comps = comps * torch.sign(comps.gather(1, idx[:, None]))
        return cls(mean, comps, evals[:d].clamp_min(0), whiten, shrinkage, n)

    # --- use ---------------------------------------------------------------------------------------------------
    def transform(self, x: torch.Tensor) -> torch.Tensor:
        """``x [..., D]`` -> ``[..., d]`` (centred, projected, scaled); float32."""
        if x.shape[-1] != self.in_dim:
            raise ValueError(f"PCA expects descriptors of size {self.in_dim}, got {tuple(x.shape)}")
        return (x.float() - self.mean.to(x.device)) @ self._proj.to(x.device)

    # --- persistence ------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"mean": self.mean.clone(), "components": self.components.clone(),
                "eigenvalues": self.eigenvalues.clone(), "whiten": self.whiten, "shrinkage": self.shrinkage,
                "num_samples": self.num_samples}

    @classmethod
    def from_state_dict(cls, sd: dict) -> "PCAWhitening":
        missing = [k for k in ("mean", "components", "eigenvalues") if k not in sd]
        if missing:
            raise ValueError(f"PCA state lacks {missing} (has {sorted(sd)})")
        return cls(sd["mean"], sd["components"], sd["eigenvalues"], bool(sd.get("whiten", True)),
                   float(sd.get("shrinkage", 0.0)), int(sd.get("num_samples", 0)))

    def save(self, path: Union[str, Path]) -> None:
        torch.save({"format": "pvslam.pca", "pca": self.state_dict()}, str(path))

    @classmethod
    def load(cls, path: Union[str, Path]) -> "PCAWhitening":
        """A file written by :meth:`save`, or a project DeiT checkpoint that carries a ``pca`` entry."""
        from pvslam_core.weights import load_torch_file

        obj = load_torch_file(path, "deit loop detector: loop.pca_file", error=ValueError)
        sd = obj.get("pca") if isinstance(obj, dict) else None
        if not isinstance(sd, dict):
            raise ValueError(f"{path}: no 'pca' entry (keys: {sorted(obj) if isinstance(obj, dict) else type(obj)})")
        try:
            return cls.from_state_dict(sd)
        except (TypeError, ValueError, AttributeError, RuntimeError) as exc:
            raise ValueError(f"{path}: the 'pca' entry cannot be used: {exc}") from None


class OnlinePCA:
    """PCA / whitening fitted on the descriptors seen so far.

    Refit policy: nothing is fitted until ``min_samples`` descriptors were seen (``transform`` is then the
    identity: raw descriptors, only L2-normalised downstream); the first fit happens at ``min_samples``, and
    each later one when the count has grown by the factor ``refit_growth`` since the last fit (geometric: a
    sequence of N keyframes costs O(log N) eigen-decompositions of D x D, ~50 ms each at D = 768).  After
    ``freeze_after`` samples (if set) the transform stops changing, so late scores stay comparable.

    Every refit changes ``version``; stores holding raw descriptors re-project them then, so all descriptors
    compared at any moment went through the same transform.
    """

    def __init__(self, dim: Optional[int] = 256, whiten: bool = True, shrinkage: float = 0.1,
                 min_samples: int = 32, refit_growth: float = 1.25, freeze_after: Optional[int] = None) -> None:
        if min_samples < 2:
            raise ValueError("min_samples must be >= 2")
        if refit_growth <= 1.0:
            raise ValueError("refit_growth must be > 1")
        if freeze_after is not None and freeze_after < min_samples:
            raise ValueError(f"freeze_after ({freeze_after}) must be >= min_samples ({min_samples})")
        self.dim, self.whiten, self.shrinkage = dim, whiten, shrinkage
        self.min_samples, self.refit_growth, self.freeze_after = int(min_samples), float(refit_growth), freeze_after
        self.n = 0  # samples in the statistics (those seen after the freeze are not counted)
        self._s1: Optional[torch.Tensor] = None  # float64 [D]
        self._s2: Optional[torch.Tensor] = None  # float64 [D, D]
        self.pca: Optional[PCAWhitening] = None
        self._n_at_fit = 0
        self.version = 0

    def update(self, x: torch.Tensor) -> bool:
        """Add descriptors ``x [B, D]`` (or ``[D]``) to the statistics; returns True if the transform was refit."""
        x = x.detach().reshape(-1, x.shape[-1]).double().cpu()
        if self._s1 is None:
            self._s1 = torch.zeros(x.shape[1], dtype=torch.float64)
            self._s2 = torch.zeros(x.shape[1], x.shape[1], dtype=torch.float64)
        elif x.shape[1] != self._s1.shape[0]:
            raise ValueError(f"descriptor size changed: {x.shape[1]} after {self._s1.shape[0]}")
        frozen = self.freeze_after is not None and self._n_at_fit >= self.freeze_after
        if frozen:
            return False
        self._s1 += x.sum(0)
        self._s2 += x.T @ x
        self.n += x.shape[0]
        due = self.n >= self.min_samples if self.pca is None else self.n >= self.refit_growth * self._n_at_fit
        if self.freeze_after is not None and self.n >= self.freeze_after:
            due = True  # the last fit, on (at least) freeze_after samples
        if not due:
            return False
        self.refit()
        return True

    def refit(self) -> None:
        if self.n < 2 or self._s1 is None:
            raise ValueError(f"cannot fit a PCA on {self.n} samples")
        self.pca = PCAWhitening.from_moments(self.n, self._s1, self._s2, self.dim, self.whiten, self.shrinkage)
        self._n_at_fit = self.n
        self.version += 1

    def transform(self, x: torch.Tensor) -> torch.Tensor:
        return x.float() if self.pca is None else self.pca.transform(x)
