"""Training pieces: the differentiable BA against the inference BA and finite differences, DROID's losses reaching
every head, and a tiny ``pvslam train frontend --plugin raft_gru`` run (CSV, plot, checkpoint, resume)."""
from __future__ import annotations

import csv
import json

import pytest
import torch

from pvslam_core.geometry.ba import dense_ba
from pvslam_core.geometry.lie import se3_exp, se3_inv, se3_mul
from pvslam_core.geometry.projective import reproject
from pvslam_core.slam.graph import FrameGraph
from pvslam_core.types import EdgeObservations, Intrinsics
from pvslam_plugins.frontends.raft_gru.losses import LossConfig, clip_losses, initial_poses
from pvslam_plugins.frontends.raft_gru.net import RaftGruNet
from pvslam_plugins.frontends.raft_gru.train_ba import ba_step
from pvslam_plugins.frontends.raft_gru.train_data import Clip, edges_within


@pytest.fixture(autouse=True)
def _keep_torch_threads():
    """Pipeline runs and the trainer set torch's (process-wide) thread count; other tests of the session compare
    against features computed with the default count (bitwise), so it is restored."""
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def _problem(N=4, h=6, w=8, seed=0, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    intr = torch.tensor([7.0, 7.0, 3.5, 2.5], dtype=dtype)
    xi = torch.zeros(N, 6, dtype=torch.float64)
    xi[:, 0] = 0.1 * torch.arange(N)
    xi[:, 3:] = 0.02 * torch.randn(N, 3, generator=gen, dtype=torch.float64)
    poses = se3_exp(xi).to(dtype)
    disps = (0.5 + 0.3 * torch.rand(N, h, w, generator=gen, dtype=torch.float64)).to(dtype)
    ii, jj = edges_within(N, 2)
    tgt, _ = reproject(poses, disps, intr, ii, jj)
    tgt = tgt + 0.3 * torch.randn(tgt.shape, generator=gen, dtype=dtype)
    wt = torch.rand(tgt.shape, generator=gen, dtype=dtype)
    eta = 0.01 * torch.rand(N, h, w, generator=gen, dtype=dtype)
    p0 = poses.clone()
    p0[2:, :3] += 0.05
    return p0, (disps * 1.1).float().to(dtype), tgt, wt, eta, intr, ii, jj


def test_ba_step_equals_the_inference_ba():
    p0, d0, tgt, wt, eta, intr, ii, jj = _problem()
    N, h, w = d0.shape
    p1, d1 = ba_step(p0, d0, tgt, wt, 0.2 * eta, intr, ii, jj, fixedp=2, damping="schur")
    g = FrameGraph(h, w, intr.float(), capacity=8)
    for k in range(N):
        g.add_keyframe(k, float(k), p0[k], d0[k].float())
    g.intrinsics = intr
    obs = EdgeObservations(ii, jj, tgt.permute(0, 3, 1, 2), wt.permute(0, 3, 1, 2), depth_damping=eta)
    dense_ba(g, obs, torch.tensor([False, False, True, True]), iters=1, dtype=torch.float64, robust=None)
    assert (g.poses - p1).abs().max() < 1e-12
    assert (g.disps.double() - d1).abs().max() < 1e-6  # the graph stores float32 inverse depths
    assert (p1 - p0).abs().max() > 1e-3  # it moved


def test_ba_step_gradients_by_finite_differences():
    p0, d0, tgt, wt, eta, intr, ii, jj = _problem(N=3, h=3, w=4, seed=1)
    tgt, wt, eta = (t.clone().requires_grad_(True) for t in (tgt, wt, eta))

    def f(tgt, wt, eta):
        p, d = ba_step(p0, d0, tgt, wt, eta, intr, ii, jj, fixedp=1)
        return torch.cat([p[1:, :3].reshape(-1), d.reshape(-1)])

    assert torch.autograd.gradcheck(f, (tgt, wt, eta), eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


def test_initial_poses_constant_velocity():
    step = se3_exp(torch.tensor([0.1, 0.0, 0.3, 0.01, 0.02, 0.0], dtype=torch.float64))
    poses = [se3_exp(torch.tensor([1.0, 2.0, 0.0, 0.0, 0.3, 0.0], dtype=torch.float64))]
    for _ in range(4):
        poses.append(se3_mul(poses[-1], step))
    gt = torch.stack(poses)
    torch.testing.assert_close(initial_poses(gt, 2), gt, atol=1e-10, rtol=0)
    assert torch.equal(initial_poses(gt, 1), gt[:1].expand(5, 7))
    assert torch.equal(initial_poses(gt, 2, "droid"), torch.cat([gt[:2], gt[1:2].expand(3, 7)]))


def _clip(droid_golden) -> Clip:
    imgs = droid_golden["images_uint8"][0, :, [2, 1, 0]].contiguous()  # 3 RGB frames 128 x 136
    poses = torch.stack([se3_exp(torch.tensor([0.02 * k, 0.0, 0.1 * k, 0.0, 0.01 * k, 0.0], dtype=torch.float64))
                         for k in range(3)])
    disps = torch.full((3, 128, 136), 0.5)
    disps[:, :20] = 0.0  # "sky"
    dyn = torch.zeros(3, 128, 136, dtype=torch.bool)
    dyn[:, 60:90, 30:60] = True
    return Clip("golden", [0, 1, 2], imgs, poses, disps, dyn, Intrinsics(110.0, 110.0, 67.5, 63.5, 136, 128))


@pytest.mark.parametrize("variant", ["droid", "pvo"])
def test_losses_reach_every_head(droid_golden, variant):
    torch.manual_seed(0)
    model = RaftGruNet(variant)
    loss, m = clip_losses(model, _clip(droid_golden), LossConfig(iters=1, radius=1))
    assert torch.isfinite(loss) and m["f_error"] > 0
    loss.backward()
    names = ["fnet.conv1.weight", "cnet.conv2.weight", "update.delta.2.weight", "update.weight.2.weight",
             "update.agg.eta.0.weight", "update.gru.convq.weight"]
    names.append("update.agg.upmask_disp.0.weight" if variant == "pvo" else "update.agg.upmask.0.weight")
    if variant == "pvo":
        names.append("update.delta_mask.2.weight")
    params = dict(model.named_parameters())
    for n in names:
        g = params[n].grad
        assert g is not None and bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0, n


def test_normalisation_keeps_the_induced_flow(droid_golden):
    """Clips are rescaled to median depth 1 (DROID divides depths by 5): the flow the ground truth induces, which
    the flow loss compares against, must not change."""
    from pvslam_plugins.frontends.raft_gru.losses import normalised

    clip = _clip(droid_golden)
    clip.disps[1, 40:] = 0.2  # uneven depth so the median is not a trivial value
    pg, dg = normalised(clip)
    intr = clip.intrinsics.vector(torch.float64)
    ii, jj = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 0])
    a, va = reproject(clip.poses, clip.disps.double(), intr, ii, jj)
    b, vb = reproject(pg, dg.double(), intr, ii, jj)
    assert bool((va == vb).all()) and float((a - b).norm(dim=-1)[va].max()) < 1e-9
    assert float(1.0 / dg[0][dg[0] > 0].median()) == pytest.approx(1.0)
    assert float((pg[:, :3] - clip.poses[:, :3]).abs().max()) > 1e-3


def test_train_run_writes_logs_checkpoint_and_resumes(tmp_path):
    from pvslam_core.training import train
    from pvslam_plugins.frontends.raft_gru.config import RaftGruConfig
    from pvslam_plugins.frontends.raft_gru.frontend import RaftGruFrontend

    common = ['scenarios=["indoor_handheld"]', "train_seeds=[1]", "val_seeds=[100]", "frames_per_sequence=6",
              "width=128", "height=128", "clip_length=3", "radius=1", "iters=1", "eval_every=1", "progress=false",
              "max_stride=1", f'data_cache="{(tmp_path / "data").as_posix()}"']
    out, summary = train("frontend", "raft_gru", None, common + ["steps=2"], tmp_path / "run")
    rows = list(csv.DictReader((out / "loss.csv").open()))
    vals = list(csv.DictReader((out / "val.csv").open()))
    assert [r["step"] for r in rows] == ["1", "2"] and [v["step"] for v in vals] == ["0", "1", "2"]
    assert (out / "loss.png").stat().st_size > 1000 and summary["steps"] == 2
    assert json.loads((out / "summary.json").read_text())["steps"] == 2
    fe = RaftGruFrontend(RaftGruConfig(weights=str(out / "model_final.pth")))
    assert fe.variant == "droid"
    _, again = train("frontend", "raft_gru", None, common + ["steps=3"], out, resume=True)
    rows = list(csv.DictReader((out / "loss.csv").open()))
    assert again["steps"] == 3 and [r["step"] for r in rows] == ["1", "2", "3"]
