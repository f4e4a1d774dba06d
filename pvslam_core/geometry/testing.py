"""Synthetic bundle-adjustment problems (a room with a box, seen by a moving camera) for tests and benchmarks.

Everything is exact: depths are ray-cast against planes and an axis-aligned box, flow targets are the
reprojections under the ground-truth poses and depths.  Noise and outliers can be added to the targets.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from ..types import EdgeObservations
from .lie import quat_rotate, se3_exp, se3_inv, se3_mul
from .projective import pixel_grid, reproject


@dataclass
class SyntheticBAProblem:
    poses: torch.Tensor  # float64 [N, 7] ground-truth T_wc
    disps: torch.Tensor  # float32 [N, h, w] ground-truth inverse depth
    intr: torch.Tensor  # float32 [4]
    ii: torch.Tensor
    jj: torch.Tensor
    target: torch.Tensor  # float32 [E, 2, h, w]
    weight: torch.Tensor  # float32 [E, 2, h, w]
    outlier: torch.Tensor  # bool [E, h, w] pixels whose target was replaced by an outlier

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.disps.shape[-2]), int(self.disps.shape[-1])

    def observed(self) -> torch.Tensor:
        """bool ``[N, h, w]``: pixels that some edge observes (weight > 0) from their keyframe."""
        seen = torch.zeros_like(self.disps, dtype=torch.bool)
        for e in range(len(self.ii)):
            seen[self.ii[e]] |= self.weight[e, 0] > 0
        return seen

    def baseline_ratio(self, poses_wc: torch.Tensor) -> float:
        """Median ratio of the distances from keyframe 0 under ``poses_wc [N, 7]`` to the ground truth's (the
        estimate's scale against the truth's, with keyframe 0 fixed)."""
        est = (poses_wc[1:, :3] - poses_wc[0, :3]).norm(dim=-1)
        true = (self.poses[1:, :3] - self.poses[0, :3]).norm(dim=-1)
        return float((est / true).median())

    def obs(self, ii: Optional[torch.Tensor] = None, jj: Optional[torch.Tensor] = None) -> EdgeObservations:
        if ii is None:
            return EdgeObservations(self.ii.clone(), self.jj.clone(), self.target.clone(), self.weight.clone())
        sel = []
        for a, b in zip(ii.tolist(), jj.tolist()):
            m = torch.nonzero((self.ii == a) & (self.jj == b)).squeeze(1)
            if len(m) == 0:
                raise KeyError(f"edge {a}->{b} not in the problem")
            sel.append(int(m[0]))
        s = torch.tensor(sel, dtype=torch.long)
        return EdgeObservations(self.ii[s].clone(), self.jj[s].clone(), self.target[s].clone(), self.weight[s].clone())

    def graph(self, poses: Optional[torch.Tensor] = None, disps: Optional[torch.Tensor] = None, device="cpu"):
        from ..slam.graph import FrameGraph

        h, w = self.shape
        g = FrameGraph(h, w, self.intr, device=device, capacity=4)
        poses = self.poses if poses is None else poses
        disps = self.disps if disps is None else disps
        for k in range(poses.shape[0]):
            g.add_keyframe(k, float(k) * 0.1, poses[k], disps[k])
        g.add_edges(self.ii, self.jj, 0)
        return g


def _raycast(origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Distance along ``dirs`` to the first hit with the room (walls at x=+-4, floor y=1.5, ceiling y=-2.5,
    back wall z=8, front wall z=-4) and a box [-1, 0.5] x [0.2, 1.5] x [3, 4.5]."""
    big = torch.full(dirs.shape[:-1], float("inf"), dtype=dirs.dtype)
    lam = big.clone()
    planes = [(0, 4.0), (0, -4.0), (1, 1.5), (1, -2.5), (2, 8.0), (2, -4.0)]
    for axis, c in planes:
        dn = dirs[..., axis]
        l = (c - origins[..., axis]) / torch.where(dn.abs() < 1e-12, torch.full_like(dn, 1e-12), dn)
        lam = torch.where((l > 1e-6) & (l < lam), l, lam)
    lo = torch.tensor([-1.0, 0.2, 3.0], dtype=dirs.dtype)
    hi = torch.tensor([0.5, 1.5, 4.5], dtype=dirs.dtype)
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t1 = (lo - origins) * inv
    t2 = (hi - origins) * inv
    tmin = torch.minimum(t1, t2).amax(-1)
    tmax = torch.maximum(t1, t2).amin(-1)
    hit = (tmax >= tmin) & (tmin > 1e-6)
    return torch.where(hit & (tmin < lam), tmin, lam)


def make_problem(
    n: int = 7,
    h: int = 30,
    w: int = 40,
    seed: int = 0,
    radius: int = 2,
    noise: float = 0.0,
    outlier_frac: float = 0.0,
    outlier_weight: float = 0.05,
    step: float = 0.25,
    edges: Optional[tuple[torch.Tensor, torch.Tensor]] = None,
    trajectory: str = "line",
    loop_edges: bool = False,
) -> SyntheticBAProblem:
    """A camera moving sideways/forward through a room with small rotations; edges ``|i - j| <= radius`` both ways.

    ``trajectory="loop"``: one turn of a circle instead; ``loop_edges`` adds ``(n-1, 0)`` and ``(0, n-1)``.
    ``noise``: Gaussian pixel noise on the targets; ``outlier_frac`` of the pixels get a random target
    (uniform over +-10 px) and their weight multiplied by ``outlier_weight`` (a frontend's low confidence).
    """
    gen = torch.Generator().manual_seed(seed)
    f = 0.9 * w
    intr = torch.tensor([f, f, (w - 1) / 2, (h - 1) / 2], dtype=torch.float32)
    poses = []
    for k in range(n):
        rot = torch.tensor([0.03, 0.06, 0.02], dtype=torch.float64) * torch.randn(3, generator=gen, dtype=torch.float64)
        if trajectory == "loop":  # one turn of a circle (radius 0.8 m), back next to the start
            a = 2 * math.pi * k / n
            t = torch.tensor([0.8 * math.sin(a), 0.0, 0.8 * (1 - math.cos(a)) - 0.5], dtype=torch.float64)
            rot[1] += 0.15 * math.sin(a)
        else:
            t = torch.tensor([step * k * 0.8 - 1.0, 0.05 * torch.randn(1, generator=gen).item(), step * k * 0.6],
                             dtype=torch.float64)
            rot[1] += -0.04 * k
        T = se3_exp(torch.cat([torch.zeros(3, dtype=torch.float64), rot]))
        T[:3] = t
        poses.append(T)
    poses = torch.stack(poses)
    grid = pixel_grid(h, w, "cpu", torch.float64)
    rays_c = torch.stack([(grid[..., 0] - float(intr[2])) / float(intr[0]),
                          (grid[..., 1] - float(intr[3])) / float(intr[1]), torch.ones(h, w, dtype=torch.float64)], -1)
    disps = []
    for k in range(n):
        dirs = quat_rotate(poses[k, 3:].expand(h, w, 4), rays_c)
        lam = _raycast(poses[k, :3].expand(h, w, 3), dirs)
        disps.append((1.0 / lam).float())  # z-depth = lam because rays have unit z in the camera frame
    disps = torch.stack(disps)
    if edges is None:
        ii, jj = [], []
        for a in range(n):
            for b in range(n):
                if a != b and abs(a - b) <= radius:
                    ii.append(a)
                    jj.append(b)
        if loop_edges:
            ii += [n - 1, 0]
            jj += [0, n - 1]
        ii, jj = torch.tensor(ii), torch.tensor(jj)
    else:
        ii, jj = edges
    coords, valid = reproject(poses, disps.double(), intr.double(), ii, jj)
    inside = (coords[..., 0] > -0.5) & (coords[..., 0] < w - 0.5) & (coords[..., 1] > -0.5) & (coords[..., 1] < h - 0.5)
    target = coords.permute(0, 3, 1, 2).clone()
    weight = (valid & inside).float().unsqueeze(1).expand(-1, 2, -1, -1).clone()
    E = len(ii)
    if noise > 0:
        target = target + noise * torch.randn(target.shape, generator=gen, dtype=target.dtype)
    outlier = torch.zeros(E, h, w, dtype=torch.bool)
    if outlier_frac > 0:
        outlier = torch.rand(E, h, w, generator=gen) < outlier_frac
        bad = (torch.rand(E, 2, h, w, generator=gen, dtype=target.dtype) - 0.5) * 20.0
        target = torch.where(outlier.unsqueeze(1), target + bad, target)
        weight = torch.where(outlier.unsqueeze(1), weight * outlier_weight, weight)
    return SyntheticBAProblem(poses, disps, intr, ii, jj, target.float(), weight, outlier)


def perturb(problem: SyntheticBAProblem, rot: float = 0.02, trans: float = 0.05, disp_rel: float = 0.2,
            fixed: tuple[int, ...] = (0,), seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Perturbed initial poses (keyframes in ``fixed`` untouched) and disparities (relative noise, smoothed)."""
    gen = torch.Generator().manual_seed(seed)
    n = problem.poses.shape[0]
    xi = torch.cat([trans * torch.randn(n, 3, generator=gen, dtype=torch.float64),
                    rot * torch.randn(n, 3, generator=gen, dtype=torch.float64)], -1)
    for k in fixed:
        xi[k] = 0
    poses = se3_mul(problem.poses, se3_exp(xi))
    h, w = problem.shape
    lowres = torch.randn(n, 1, 4, 5, generator=gen)
    field = torch.nn.functional.interpolate(lowres, size=(h, w), mode="bilinear", align_corners=False)[:, 0]
    disps = problem.disps * (1.0 + disp_rel * field).clamp(min=0.3)
    return poses, disps


def scale_drifted(problem: SyntheticBAProblem, rate: float = 0.97, yaw_drift: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
    """A monocular-style drifted estimate: relative motions re-chained with keyframe k's translation scaled by
    ``rate**k`` (plus a small yaw drift), and each keyframe's depth scaled by the same factor."""
    n = problem.poses.shape[0]
    c = torch.tensor([rate ** k for k in range(n)], dtype=torch.float64)
    poses = [problem.poses[0].clone()]
    drift = se3_exp(torch.tensor([0, 0, 0, 0, yaw_drift, 0], dtype=torch.float64))
    for k in range(n - 1):
        rel = se3_mul(se3_inv(problem.poses[k]), problem.poses[k + 1])
        rel[:3] = rel[:3] * c[k]
        poses.append(se3_mul(se3_mul(poses[-1], rel), drift))
    poses = torch.stack(poses)
    disps = problem.disps / c.float().reshape(n, 1, 1)
    return poses, disps


def circle_poses(n: int, radius: float) -> torch.Tensor:
    """``[n, 7]`` T_wc on a horizontal circle of ``radius`` m, each camera turned with the circle (one lap)."""
    poses = []
    for k in range(n):
        a = 2 * math.pi * k / n
        T = se3_exp(torch.tensor([0, 0, 0, 0, -a, 0.0], dtype=torch.float64))
        T[:3] = torch.tensor([radius * math.cos(a), 0, radius * math.sin(a)], dtype=torch.float64)
        poses.append(T)
    return torch.stack(poses)


@dataclass
class DriftedLoop:
    """A Sim(3) pose-graph problem (the arguments of ``sim3_pose_graph``) and its truth: see :func:`drifted_loop`."""

    gt: torch.Tensor  # [n, 7] true T_wc
    est: torch.Tensor  # [n, 7] the drifted odometry chain
    drift: torch.Tensor  # [n] scale of keyframe k's translation, rate ** k
    S: torch.Tensor  # [n, 8] initial Sim(3) poses (est, scale 1)
    ii: torch.Tensor
    jj: torch.Tensor
    Z: torch.Tensor  # [E, 8] relative Sim(3) measurements (odometry, then the loop edge (n-1, 0))
    fixed: torch.Tensor  # bool [n], keyframe 0
    weight: torch.Tensor  # [E], the loop edge loop_weight

    def args(self) -> tuple:
        return self.S, self.ii, self.jj, self.Z, self.fixed, self.weight


def drifted_loop(n: int, radius: float, rate: float, yaw_drift: float, loop_weight: float = 10.0) -> DriftedLoop:
    """A lap of :func:`circle_poses` as monocular odometry sees it (keyframe k's relative translation scaled by
    ``rate ** k``, a yaw drift per keyframe), the odometry chain as Sim(3) edges and one loop edge ``(n-1, 0)``
    measured from the truth in keyframe n-1's drifted scale: a closure after a lap."""
    from .lie import sim3_from_se3
    from .pose_graph import odometry_measurements

    gt = circle_poses(n, radius)
    c = torch.tensor([rate ** k for k in range(n)], dtype=torch.float64)
    yaw = se3_exp(torch.tensor([0, 0, 0, 0, yaw_drift, 0], dtype=torch.float64))
    est = [gt[0]]
    for k in range(n - 1):
        rel = se3_mul(se3_inv(gt[k]), gt[k + 1])
        rel[:3] *= c[k]
        est.append(se3_mul(est[-1], se3_mul(rel, yaw)))
    est = torch.stack(est)
    S = sim3_from_se3(est, 1.0)
    ii, jj, Z = odometry_measurements(S)
    Zl = sim3_from_se3(se3_mul(se3_inv(gt[n - 1]), gt[0]), c[n - 1] / c[0])
    Zl[:3] *= c[n - 1]  # measured in n-1's (drifted) scale
    weight = torch.ones(len(ii) + 1, dtype=torch.float64)
    weight[-1] = loop_weight
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[0] = True
    return DriftedLoop(gt, est, c, S, torch.cat([ii, torch.tensor([n - 1])]), torch.cat([jj, torch.tensor([0])]),
                       torch.cat([Z, Zl[None]]), fixed, weight)


def umeyama_ate(est_xyz: torch.Tensor, gt_xyz: torch.Tensor, scale: bool = True) -> float:
    """RMSE of positions after the best Sim(3) (or SE(3)) alignment of ``est`` onto ``gt``."""
    x, y = est_xyz.double(), gt_xyz.double()
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    cov = yc.T @ xc / x.shape[0]
    U, D, Vt = torch.linalg.svd(cov)
    Sg = torch.eye(3, dtype=torch.float64)
    if torch.det(U) * torch.det(Vt) < 0:
        Sg[2, 2] = -1
    R = U @ Sg @ Vt
    s = (D * torch.diagonal(Sg)).sum() / xc.pow(2).sum(1).mean() if scale else torch.tensor(1.0, dtype=torch.float64)
    t = my - s * R @ mx
    aligned = s * x @ R.T + t
    return float(torch.sqrt(((aligned - y) ** 2).sum(1).mean()))
