"""DROID-SLAM's training forward pass and losses (and PVO's mask loss), on one clip.

Forward (DROID ``DroidNet.forward``): features of the ``N`` frames; edges ``0 < |i - j| <= radius``; poses start with
the first ``fixedp`` (2) at the ground truth, inverse depths at 1; then
``iters`` times: lookup at the current reprojection, one update step, ``target = coords1 + delta``, ``ba_iters`` (2)
steps of the differentiable BA (:mod:`.train_ba`) with the predicted weights and damping, reprojection.  As upstream,
poses, depths, reprojection and target are detached at the start of each iteration (the GRU state is not), so each
iteration's losses train that iteration's update through the BA.

Losses, each summed over iterations with weight ``gamma ** (iters - 1 - it)`` (gamma 0.9):

* geodesic: ``|tau| + |phi|`` of ``log(dG dP^-1)`` per edge, ``dG``/``dP`` the estimated / true relative poses (no
  scale fit: two fixed ground-truth poses set the scale);
* residual: mean ``|target - reprojection after BA|`` over valid pixels (``valid * r``);
* flow: mean end-point error, at the training resolution, between the flow the *estimate* induces (poses after BA,
  inverse depth convex-upsampled with the learned mask) and the one the ground truth induces, on the edges
  ``|i - j| = 1``, over valid static pixels (the dynamic masks remove moving objects, whose flow the ground-truth
  poses and depth do not explain);
* mask (PVO only): binary cross-entropy of ``sigmoid(raw_mask)`` (bilinearly upsampled, PVO's ``upsample_inter``)
  against the ground-truth static mask of each edge's source frame.

Weights (DROID): ``10 geo + 0.01 res + 0.05 flow`` (+ PVO's ``0.01 mask``).  Each clip is rescaled so that frame 0's
median depth is 1 (as DROID divides TartanAir depths by 5), which makes the inverse-depth initialisation at 1
meaningful on every scenario.

One deviation from DROID: the free poses start from the constant-velocity extrapolation of the two fixed ones, not at
frame ``fixedp - 1``'s pose.  With DROID's start, even *exact* targets left the BA (ours and the inference BA alike)
in a wrong local minimum on forward-driving clips (23 deg off after 30 iterations, constant initial depth), so
a short CPU training would mostly learn to escape a bad start; from the extrapolation 12 BA iterations with exact
targets reach the ground truth.  (The inference mapper also starts new keyframes from a motion prediction.)  The
price: a network that keeps its weights low leaves the poses near the (good) start, so early in training the pose
loss falls faster than the flow loss; ``pose_init = "droid"`` restores DROID's start for longer runs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from pvslam_core.geometry.lie import se3_inv, se3_log, se3_mul
from pvslam_core.geometry.projective import reproject

from .corr import CorrVolume, coords_grid
from .edge_step import motion_input, pvo_weight
from .encoders import frames_to_images
from .train_ba import ba_step
from .train_data import Clip, edges_within
from .upsample import upsample_disp, upsample_inter


@dataclass
class LossConfig:
    iters: int = 6  # update steps (DROID trains with 15)
    radius: int = 2  # edges |i - j| <= radius
    fixedp: int = 2
    ba_iters: int = 2
    gamma: float = 0.9
    w_geo: float = 10.0
    w_res: float = 0.01
    w_flow: float = 0.05
    w_mask: float = 0.01
    mask_thresh: float = 0.5
    panoptic_offset: float = 10.0
    convention: str = "paper"
    pose_init: str = "constant_velocity"  # or "droid": every free pose at frame fixedp - 1's (module docstring)


def normalised(clip: Clip) -> tuple[torch.Tensor, torch.Tensor]:
    """Ground-truth ``poses [N, 7]`` and ``disps [N, H, W]`` rescaled so frame 0's median valid depth is 1."""
    d0 = clip.disps[0][clip.disps[0] > 0]
    s = float(1.0 / d0.median()) if d0.numel() else 1.0
    poses = clip.poses.clone()
    poses[:, :3] = poses[:, :3] / s
    return poses, clip.disps * s


def initial_poses(poses_gt: torch.Tensor, fixedp: int, mode: str = "constant_velocity") -> torch.Tensor:
    """The first ``fixedp`` ground-truth poses, then the constant-velocity extrapolation of the last two of them
    (``mode="droid"``: every free pose at frame ``fixedp - 1``'s, DROID's start)."""
    if mode not in ("constant_velocity", "droid"):
        raise ValueError(f"pose_init must be 'constant_velocity' or 'droid', got {mode!r}")
    if mode == "droid":
        return torch.cat([poses_gt[:fixedp], poses_gt[fixedp - 1: fixedp].expand(poses_gt.shape[0] - fixedp, 7)])
    if fixedp < 2:
        return torch.cat([poses_gt[:1], poses_gt[:1].expand(poses_gt.shape[0] - 1, 7)])
    step = se3_mul(se3_inv(poses_gt[fixedp - 2: fixedp - 1]), poses_gt[fixedp - 1: fixedp])  # T_{k-1}^-1 T_k
    out = [poses_gt[:fixedp]]
    cur = poses_gt[fixedp - 1: fixedp]
    for _ in range(poses_gt.shape[0] - fixedp):
        cur = se3_mul(cur, step)
        out.append(cur)
    return torch.cat(out)


def geodesic(poses: torch.Tensor, poses_gt: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor):
    """Per-edge translation and rotation errors ``(|tau|, |phi|)`` of the relative poses ``i -> j``."""
    dG = se3_mul(se3_inv(poses[jj]), poses[ii])
    dP = se3_mul(se3_inv(poses_gt[jj]), poses_gt[ii])
    d = se3_log(se3_mul(dG, se3_inv(dP)))
    return d[:, :3].norm(dim=-1), d[:, 3:].norm(dim=-1)


def clip_losses(model, clip: Clip, cfg: LossConfig) -> tuple[torch.Tensor, dict]:
    """Unrolled forward pass and DROID's losses on one clip; returns ``(total loss, metrics)``."""
    variant = model.variant
    dev = next(model.parameters()).device
    N = clip.images.shape[0]
    poses_gt, disps_gt = normalised(clip)
    poses_gt, disps_gt = poses_gt.to(dev).float(), disps_gt.to(dev).float()
    intr = clip.intrinsics.vector(torch.float32, dev)
    intr8 = clip.intrinsics.scaled(1.0 / 8).vector(torch.float32, dev)
    ii, jj = (t.to(dev) for t in edges_within(N, cfg.radius))
    feats = model.features(frames_to_images(clip.images.to(dev)), "rgb")
    h, w = feats.fmap.shape[-2:]
    corr_fn = CorrVolume.from_edges(feats.fmap, ii, jj)
    net, inp = feats.net[:, ii], feats.inp[:, ii]
    coords0 = coords_grid(h, w, device=dev)
    poses = initial_poses(poses_gt, cfg.fixedp, cfg.pose_init)
    disps = torch.ones(N, h, w, device=dev)
    coords1, _ = reproject(poses, disps, intr8, ii, jj)
    target = coords1.clone()
    E = int(ii.numel())
    raw_mask = torch.zeros(E, h, w, 2, device=dev) if variant == "pvo" else None
    delta_dy = torch.zeros(E, h, w, 2, device=dev) if variant == "pvo" else None
    # ground truth for the flow loss: |i - j| = 1 edges at the training resolution, valid static pixels
    fi, fj = ii[(ii - jj).abs() == 1], jj[(ii - jj).abs() == 1]
    flow_gt, val_gt = reproject(poses_gt, disps_gt, intr, fi, fj)
    val_gt = val_gt & (disps_gt[fi] > 0) & ~clip.dynamic.to(dev)[fi]
    static_gt = (~clip.dynamic.to(dev)[ii]).float()  # PVO labels: 1 = static

    geo = res = flow = mask = torch.zeros((), device=dev)
    for it in range(cfg.iters):
        wgt = cfg.gamma ** (cfg.iters - 1 - it)
        poses, disps, coords1, target = poses.detach(), disps.detach(), coords1.detach(), target.detach()
        if raw_mask is not None:
            raw_mask, delta_dy = raw_mask.detach(), delta_dy.detach()
        corr = corr_fn(coords1[None])
        motion = motion_input(variant, coords0, coords1[None], target[None],
                              None if delta_dy is None else delta_dy[None],
                              None if raw_mask is None else raw_mask[None], training=True)
        out = model.update(net, inp, corr, motion, ii, jj)
        net = out.net
        target = coords1 + out.delta[0]
        if variant == "pvo":
            raw_mask = raw_mask + out.delta_m[0]
            dyn_c = (torch.sigmoid(raw_mask) < cfg.mask_thresh).float().detach()
            weight = pvo_weight(out.weight[0], dyn_c, cfg.panoptic_offset, cfg.convention)
            delta_dy = out.delta_dy[0] * dyn_c
            prob = upsample_inter(torch.sigmoid(raw_mask)[None])[0].clamp(1e-6, 1 - 1e-6)  # (E, H, W, 2)
            mask = mask + wgt * F.binary_cross_entropy(prob, static_gt[..., None].expand_as(prob))
        else:
            weight = out.weight[0]
        eta = torch.zeros(N, h, w, device=dev).index_copy(0, out.frames, out.eta[0])
        for _ in range(cfg.ba_iters):
            poses, disps = ba_step(poses, disps, target, weight, eta, intr8, ii, jj, fixedp=cfg.fixedp)
        coords1, valid = reproject(poses, disps, intr8, ii, jj)
        resid = valid[..., None] * (target - coords1)
        res = res + wgt * resid.abs().mean()
        t_err, r_err = geodesic(poses, poses_gt, ii, jj)
        geo = geo + wgt * (t_err.mean() + r_err.mean())
        upmask = torch.zeros(1, N, *out.upmask.shape[2:], device=dev).index_copy(1, out.frames, out.upmask)
        disp_up = upsample_disp(disps[None], upmask)[0]
        flow_est, val_est = reproject(poses, disp_up, intr, fi, fj)
        v = (val_gt & val_est).float()
        epe = v * (flow_est - flow_gt).norm(dim=-1)
        flow = flow + wgt * epe.mean()
    loss = cfg.w_geo * geo + cfg.w_res * res + cfg.w_flow * flow + (cfg.w_mask * mask if variant == "pvo" else 0.0)
    with torch.no_grad():
        good = v > 0.5
        f_err = float(epe[good].mean()) if bool(good.any()) else float("nan")
        H, W = clip.images.shape[-2:]
        inside = good & (flow_gt[..., 0] >= 0) & (flow_gt[..., 0] <= W - 1) & (flow_gt[..., 1] >= 0) & \
            (flow_gt[..., 1] <= H - 1)  # pixels that stay in view (their depth is observable from this edge)
        metrics = {"loss": float(loss), "geo": float(geo), "res": float(res), "flow": float(flow),
                   "f_error": f_err, "f_error_inview": float(epe[inside].mean()) if bool(inside.any()) else f_err,
                   "1px": float((epe[good] < 1.0).float().mean()) if bool(good.any()) else 0.0,
                   "rot_deg": float(r_err.mean()) * 180.0 / math.pi, "tr_err": float(t_err.mean())}
        if variant == "pvo":
            metrics["mask"] = float(mask)
    return loss, metrics
