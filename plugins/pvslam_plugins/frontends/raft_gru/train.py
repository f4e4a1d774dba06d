"""``pvslam train frontend --plugin raft_gru``: DROID-SLAM's training (losses through a differentiable dense BA,
:mod:`.losses`) on clips of the built-in synthetic generator, at a reduced resolution and clip length that fit a CPU.

    pvslam train frontend --plugin raft_gru --out runs/rg                       # defaults below
    pvslam train frontend --plugin raft_gru --out runs/rg --resume              # continue after an interruption
    pvslam train frontend --plugin raft_gru --out runs/of --set overfit=true    # one clip: proves losses/gradients

Data: ``frames_per_sequence`` frames of every scenario in ``scenarios`` for each of ``train_seeds`` (rendered once
into ``data_cache``); a training sample is a random clip of ``clip_length`` frames whose consecutive-frame flow lies
in ``flow_range`` (1/8 px); validation on fixed clips of ``val_seeds`` (held out).  ``overfit = true`` trains and
validates on one clip (the first validation clip).

AdamW, linear warm-up and cosine decay over the run's progress ``max(step / steps, minutes / time_budget_min)`` (a
shared machine's speed is unknown in advance, so the schedule always completes its decay), gradient-norm clip 1
(DROID).  Written into the output folder: ``last.pt`` (model, optimiser, generator, step; every
``checkpoint_every`` steps and on Ctrl-C; ``--resume`` continues from it), ``loss.csv`` (one row per step),
``val.csv`` (one row per evaluation), ``loss.png``, ``model_final.pth`` (pvslam checkpoint format, loadable as the
frontend's ``weights``).
"""
from __future__ import annotations

import csv
import math
import time
from pathlib import Path
from typing import Literal, Optional

import torch
from pydantic import Field, field_validator, model_validator

from pvslam_core.config_base import PluginConfig
from pvslam_core.training import TrainingLoop, prepare_run

__all__ = ["TrainConfig", "run"]

DEFAULT_SCENARIOS = ("driving_loop", "moving_vehicles", "indoor_handheld", "handheld_fast", "indoor_textureless",
                     "busy_street", "forward_low_parallax", "driving_city")
TERMS = ("loss", "geo", "res", "flow", "f_error", "f_error_inview", "1px", "rot_deg", "tr_err")


class TrainConfig(PluginConfig):
    variant: Literal["droid", "pvo"] = Field("droid", description="network variant (pvo adds the mask loss)")
    init: Optional[str] = Field(None, description="start from these weights (catalogue name or path; null = random)")
    scenarios: list[str] = Field(list(DEFAULT_SCENARIOS), description="synthetic scenarios to train/validate on")
    train_seeds: list[int] = Field([1, 2, 3], description="generator seeds of the training sequences")
    val_seeds: list[int] = Field([100], description="held-out generator seeds for validation")
    frames_per_sequence: int = Field(48, ge=4, description="frames rendered per (scenario, seed)")
    width: int = Field(192, ge=128, description="training image width (multiple of 8)")
    height: int = Field(128, ge=128, description="training image height (multiple of 8)")
    clip_length: int = Field(4, ge=3, description="frames per clip (DROID: 7)")
    radius: int = Field(2, ge=1, description="edges between frames with |i - j| <= radius, both directions")
    iters: int = Field(6, ge=1, description="update steps per clip (DROID: 15), 2 BA iterations each")
    flow_range: tuple[float, float] = Field((1.0, 6.0), description="consecutive-frame mean flow of a clip (1/8 px)")
    max_stride: int = Field(6, ge=1, description="largest frame stride tried when sampling a clip")
    steps: int = Field(2000, ge=1, description="optimisation steps at most (see time_budget_min)")
    time_budget_min: float = Field(100.0, gt=0, description="training minutes at most (rendering comes on top)")
    lr: float = Field(2.5e-4, gt=0, description="peak learning rate (DROID: 2.5e-4)")
    weight_decay: float = Field(1e-5, ge=0, description="AdamW weight decay")
    warmup: int = Field(20, ge=0, description="steps of linear warm-up")
    final_lr_fraction: float = Field(0.05, ge=0, le=1, description="cosine decay ends at lr * this")
    grad_clip: float = Field(1.0, gt=0, description="gradient-norm clip (DROID: 1.0)")
    w_geo: float = Field(10.0, ge=0, description="weight of the geodesic pose loss (DROID 10)")
    w_res: float = Field(0.01, ge=0, description="weight of the residual loss (DROID 0.01)")
    w_flow: float = Field(0.05, ge=0, description="weight of the induced-flow loss (DROID 0.05)")
    w_mask: float = Field(0.01, ge=0, description="weight of PVO's mask loss (PVO 0.01)")
    pose_init: Literal["constant_velocity", "droid"] = Field(
        "constant_velocity", description="start of the free poses: extrapolation of the two fixed ones, or DROID's "
        "(all at the second frame's pose; harder: see losses.py)")
    overfit: bool = Field(False, description="train and validate on one clip (checks losses and gradients)")
    eval_every: int = Field(25, ge=1, description="validation every this many steps")
    val_clips_per_sequence: int = Field(1, ge=1, description="fixed validation clips per (scenario, seed)")
    checkpoint_every: int = Field(25, ge=1, description="write the resumable state and the plot every this many steps")
    threads: int = Field(1, ge=0, description="torch threads (0 = torch's default); 1 is fastest on a loaded "
                         "2-core machine (OpenMP threads wait for each other)")
    seed: int = Field(0, description="seed of the initialisation and the clip sampling")
    data_cache: Optional[str] = Field(None, description="folder for the rendered sequences (default: OUT/data)")
    progress: bool = Field(True, description="progress bar (only on a terminal)")

    @field_validator("scenarios")
    @classmethod
    def _known(cls, v: list[str]) -> list[str]:
        from pvslam_plugins.datasets.synthetic.generator import SCENARIOS

        unknown = [s for s in v if s not in SCENARIOS]
        if unknown:
            raise ValueError(f"unknown synthetic scenarios {unknown}; available: {', '.join(SCENARIOS)}")
        return v

    @model_validator(mode="after")
    def _check(self):
        from .train_data import check_size

        why = check_size(self.width, self.height)
        if why:
            raise ValueError(why)
        common = set(self.val_seeds) & set(self.train_seeds)
        if common and not self.overfit:
            raise ValueError(f"val_seeds {sorted(common)} are also train_seeds; validation seeds must be held out")
        if self.frames_per_sequence < self.clip_length:
            raise ValueError("frames_per_sequence must be >= clip_length")
        return self


def progress_of(cfg: TrainConfig, step: int, elapsed_s: float) -> float:
    return max(step / cfg.steps, elapsed_s / (60.0 * cfg.time_budget_min))


def lr_at(cfg: TrainConfig, step: int, progress: float) -> float:
    if step < cfg.warmup:
        return cfg.lr * (0.1 + 0.9 * step / max(cfg.warmup, 1))
    start = cfg.warmup / cfg.steps
    t = min(max((progress - start) / max(1.0 - start, 1e-9), 0.0), 1.0)
    lo = cfg.final_lr_fraction
    return cfg.lr * (lo + (1 - lo) * 0.5 * (1 + math.cos(math.pi * t)))


def loss_config(cfg: TrainConfig):
    from .losses import LossConfig

    return LossConfig(iters=cfg.iters, radius=cfg.radius, w_geo=cfg.w_geo, w_res=cfg.w_res, w_flow=cfg.w_flow,
                      w_mask=cfg.w_mask, pose_init=cfg.pose_init)


def evaluate(model, clips, lcfg) -> dict:
    """Mean losses/metrics over ``clips`` (no gradients; the BA runs as in training)."""
    from .losses import clip_losses

    sums: dict[str, float] = {}
    was = model.training
    model.eval()
    with torch.no_grad():
        for c in clips:
            _, m = clip_losses(model, c, lcfg)
            for k, v in m.items():
                sums[k] = sums.get(k, 0.0) + v
    model.train(was)
    return {k: v / max(len(clips), 1) for k, v in sums.items()}


def write_plot(csv_path: Path, val_path: Path, png_path: Path) -> None:
    """Training loss (moving mean) and validation loss / flow error against the step."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = list(csv.DictReader(csv_path.open())) if csv_path.is_file() else []
    vals = list(csv.DictReader(val_path.open())) if val_path.is_file() else []
    if not rows and not vals:
        return
    fig = Figure(figsize=(11, 4.5))
    FigureCanvasAgg(fig)
    ax, bx = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    if rows:
        steps = [int(r["step"]) for r in rows]
        win = max(1, len(rows) // 40)
        for key, lw in (("loss", 2.0), ("flow", 1.0), ("geo", 1.0)):
            v = torch.tensor([float(r[key]) for r in rows])
            sm = torch.nn.functional.avg_pool1d(v[None, None], win, 1, 0, count_include_pad=False)[0, 0]
            ax.plot(steps[win - 1:], sm.tolist(), lw=lw, label=f"train {key} (mean of {win})")
        v = torch.tensor([float(r["f_error"]) for r in rows])
        sm = torch.nn.functional.avg_pool1d(v[None, None], win, 1, 0, count_include_pad=False)[0, 0]
        bx.plot(steps[win - 1:], sm.tolist(), label=f"train (mean of {win})")
    if vals:
        vs = [int(r["step"]) for r in vals]
        ax.plot(vs, [float(r["loss"]) for r in vals], "o-", color="k", label="held-out loss")
        bx.plot(vs, [float(r["f_error"]) for r in vals], "o-", color="k", label="held-out")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_title("loss")
    bx.set_xlabel("step")
    bx.set_title("flow end-point error (training px)")
    for a in (ax, bx):
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)


def _load_data(cfg: TrainConfig, cache: Path):
    from tqdm import tqdm

    from .train_data import fixed_clips, load_sequence

    def seqs(seeds, desc):
        jobs = [(s, seed) for seed in seeds for s in cfg.scenarios]
        return [load_sequence(cache, s, seed, cfg.frames_per_sequence, cfg.width, cfg.height)
                for s, seed in tqdm(jobs, desc=desc, disable=not cfg.progress, leave=False)]

    val_seqs = seqs(cfg.val_seeds, "render validation sequences")
    val = fixed_clips(val_seqs, cfg.val_clips_per_sequence, cfg.clip_length, cfg.seed + 1, cfg.flow_range,
                      cfg.max_stride)
    if cfg.overfit:
        return [], val[:1]
    return seqs(cfg.train_seeds, "render training sequences"), val


class RaftGruLoop(TrainingLoop):
    """The shared loop with this trainer's clips (a random sequence and clip per step from the generator; the one
    validation clip when ``overfit``), DROID's losses and the held-out validation every ``eval_every`` steps."""

    log_fields = ["step", "elapsed_s", "lr", "clip", *TERMS]
    val_file, val_fields = "val.csv", ["step", "elapsed_s", *TERMS]
    desc = "train raft_gru"

    def __init__(self, cfg: TrainConfig, out: Path, model, train_seqs: list, val: list, resume: bool, opt,
                 gen) -> None:
        super().__init__(cfg, out, model, opt, gen, resume, cfg.steps)
        self.grad_clip, self.checkpoint_every = cfg.grad_clip, cfg.checkpoint_every
        self.train_seqs, self.val, self.lcfg = train_seqs, val, loss_config(cfg)
        self.clip, self.last_val = None, None

    def stop_reason(self) -> Optional[str]:
        if progress_of(self.cfg, self.step, self.elapsed) < 1.0:
            return None
        return "steps" if self.step >= self.cfg.steps else "time budget"

    def learning_rate(self) -> float:
        return lr_at(self.cfg, self.step, progress_of(self.cfg, self.step, self.elapsed))

    def loss(self) -> tuple[torch.Tensor, dict]:
        from .losses import clip_losses
        from .train_data import sample_clip

        cfg = self.cfg
        if cfg.overfit:
            self.clip = self.val[0]
        else:
            seq = self.train_seqs[int(torch.randint(len(self.train_seqs), (1,), generator=self.generator))]
            self.clip = sample_clip(seq, cfg.clip_length, self.generator, cfg.flow_range, cfg.max_stride)
        return clip_losses(self.model, self.clip, self.lcfg)

    def failed_batch(self) -> str:
        return f" on {self.clip.name} frames {self.clip.frames}"

    def log_row(self, values: dict, lr: float) -> dict:
        c = self.clip
        return {"step": self.step, "elapsed_s": f"{self.elapsed:.1f}", "lr": f"{lr:.3g}",
                "clip": f"{c.name}:{c.frames[0]}+{c.frames[1] - c.frames[0]}",
                **{k: f"{values[k]:.5f}" for k in TERMS}}

    def postfix(self, values: dict) -> dict:
        return {"loss": f"{values['loss']:.3f}", "epe": f"{values['f_error']:.2f}", "min": f"{self.elapsed / 60:.0f}"}

    def validate(self) -> dict:
        m = evaluate(self.model, self.val, self.lcfg)
        self.last_val = m
        return {"step": self.step, "elapsed_s": f"{self.elapsed:.1f}",
                **{k: f"{m.get(k, float('nan')):.5f}" for k in TERMS}}

    def validation_due(self) -> bool:
        return self.step % self.cfg.eval_every == 0

    def final_validation(self, steps_run: int) -> bool:
        return not self.validation_due()

    def on_checkpoint(self) -> None:
        write_plot(self.out / self.log_file, self.out / self.val_file, self.out / "loss.png")


def _model(cfg: TrainConfig):
    """A new network, or the ``init`` weights made trainable."""
    from .frontend import RaftGruConfig, load_network
    from .net import RaftGruNet

    if cfg.init is None:
        return RaftGruNet(cfg.variant)
    model = load_network(RaftGruConfig(weights=cfg.init, variant=cfg.variant))
    for p in model.parameters():
        p.requires_grad_(True)
    return model


def run(cfg: TrainConfig, out: Path, resume: bool) -> dict:
    """The registered trainer (see the module docstring); returns the summary."""
    from .checkpoint import save_checkpoint

    out, cache = prepare_run(cfg, out)
    model = _model(cfg)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    gen = torch.Generator().manual_seed(cfg.seed)
    t_data = time.perf_counter()
    train_seqs, val = _load_data(cfg, cache)
    data_s = time.perf_counter() - t_data
    loop = RaftGruLoop(cfg, out, model, train_seqs, val, resume, opt, gen)
    first_val = None
    if loop.step == 0:
        loop.run_validation()
        first_val = loop.last_val
    stopped = loop.run()
    final_val = loop.last_val if loop.final_val else None
    val_path = out / loop.val_file
    write_plot(out / loop.log_file, val_path, out / "loss.png")
    model.eval()
    save_checkpoint(out / "model_final.pth", model,
                    meta={"trained_on": "pvslam synthetic", "steps": loop.step,
                          "train_minutes": round(loop.elapsed / 60, 2), "width": cfg.width, "height": cfg.height,
                          "scenarios": list(cfg.scenarios), "train_seeds": list(cfg.train_seeds),
                          "overfit": cfg.overfit})
    vals = list(csv.DictReader(val_path.open()))
    first = vals[0] if vals else {}
    final = vals[-1] if vals else {}
    return {
        "steps": loop.step, "stopped_by": stopped, "train_minutes": round(loop.elapsed / 60, 2),
        "data_minutes": round(data_s / 60, 2), "val_clips": len(val),
        "val_loss_first": float(first.get("loss", "nan")), "val_loss_final": float(final.get("loss", "nan")),
        "val_f_error_first": float(first.get("f_error", "nan")),
        "val_f_error_final": float(final.get("f_error", "nan")),
        "val_f_error_best": min((float(r["f_error"]) for r in vals), default=float("nan")),
        "checkpoint": str(out / "model_final.pth"),
        "first_val": first_val, "final_val": final_val,
    }
