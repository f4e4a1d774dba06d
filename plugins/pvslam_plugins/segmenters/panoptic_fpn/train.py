"""``pvslam train segmenter --plugin panoptic_fpn``: the reduced PanopticFPN trained from scratch on the built-in
synthetic scenarios' panoptic labels.

    pvslam train segmenter --plugin panoptic_fpn --out runs/pfpn            # defaults below
    pvslam train segmenter --plugin panoptic_fpn --out runs/pfpn --resume   # continue after an interruption

Data: ``frames_per_sequence`` frames spread over every scenario in ``scenarios`` for each of ``train_seeds``;
validation on ``val_seeds`` (held out: no training frame comes from them).  ``domain_seeds`` add frames rendered
with the generator's domain randomisation (its ``"train"`` split; the held-out texture families and thing sizes
never reach training); ``init_weights`` starts from a checkpoint instead of a random initialisation.  AdamW with a
linear warm-up and a cosine decay over the run's progress, ``max(iteration / iterations, minutes /
time_budget_min)``: on a shared machine of unknown speed the run ends on whichever limit comes first with its
learning rate fully decayed (the summary says which).  Written into the output folder: ``last.pt`` (model +
optimiser + generator state, every ``checkpoint_every`` iterations and on Ctrl-C; ``--resume`` continues from it),
``loss.csv`` (one row per iteration), ``loss.png``, ``model_final.pth`` (pvslam's PanopticFPN format, loadable as
``weights``), ``eval.json`` and ``eval.md`` (PQ/SQ/RQ on the validation seeds, per class).
"""
from __future__ import annotations

import csv
import json
import math
import time
from pathlib import Path
from typing import Optional

import torch
from pydantic import Field, field_validator

from pvslam_core.config_base import PluginConfig
from pvslam_core.training import TrainingLoop, prepare_run

__all__ = ["TrainConfig", "run", "DEFAULT_SCENARIOS"]

DEFAULT_SCENARIOS = ("driving_loop", "moving_vehicles", "indoor_handheld", "handheld_fast", "indoor_textureless",
                     "busy_street", "forward_low_parallax", "driving_city")
TRAINING_DOMAIN = "train"  # the generator's domain split of the domain_seeds frames; its held-out split never trains
LOSS_TERMS = ("loss_sem_seg", "loss_rpn_cls", "loss_rpn_loc", "loss_cls", "loss_box_reg", "loss_mask")


class TrainConfig(PluginConfig):
    scenarios: list[str] = Field(list(DEFAULT_SCENARIOS), description="synthetic scenarios to train and validate on")
    train_seeds: list[int] = Field([1, 2, 3, 4, 5, 6, 7, 8], description="generator seeds of the training frames")
    domain_seeds: list[int] = Field([], description="generator seeds rendered with domain randomisation (its "
                                    "training split: other textures, sizes, light, camera) as extra training frames")
    val_seeds: list[int] = Field([100, 101], description="held-out generator seeds for validation")
    init_weights: Optional[str] = Field(None, description="start from these PanopticFPN weights (a pvslam "
                                        "checkpoint) instead of a random initialisation: fine-tuning")
    frames_per_sequence: int = Field(24, ge=1, description="training frames per (scenario, seed), evenly spaced")
    val_frames_per_sequence: int = Field(8, ge=1, description="validation frames per (scenario, seed)")
    width: int = Field(320, ge=32, description="rendered frame width (px)")
    height: int = Field(240, ge=32, description="rendered frame height (px)")
    iterations: int = Field(6000, ge=1, description="iterations at most (see time_budget_min)")
    batch_size: int = Field(4, ge=1, description="frames per iteration")
    lr: float = Field(1e-3, gt=0, description="peak learning rate (AdamW)")
    weight_decay: float = Field(1e-4, ge=0, description="AdamW weight decay")
    warmup: int = Field(200, ge=0, description="iterations of linear learning-rate warm-up")
    final_lr_fraction: float = Field(0.02, ge=0, le=1, description="cosine decay ends at lr * this")
    grad_clip: float = Field(10.0, gt=0, description="gradient-norm clip")
    crop: Optional[tuple[int, int]] = Field((192, 256), description="training crop (h, w); null = whole frames")
    scale: tuple[float, float] = Field((0.75, 1.25), description="random rescale range before the crop")
    min_instance_area: int = Field(8, ge=1, description="thing instances smaller than this (px) are no targets")
    checkpoint_every: int = Field(50, ge=1, description="write the resumable state every this many iterations")
    time_budget_min: float = Field(100.0, gt=0, description="training minutes at most (rendering and evaluation "
                                   "come on top: ~5 + ~2 min with the defaults)")
    threads: int = Field(1, ge=0, description="torch threads (0 = torch's default); more threads wait for each other "
                         "on a busy machine (docs/decisions.md: train.threads)")
    seed: int = Field(0, description="seed of the initialisation, the batches and the augmentation")
    data_cache: Optional[str] = Field(None, description="folder of the rendered-frame cache (default: OUT/data)")
    eval_min_gt_area: int = Field(64, ge=0, description="also report PQ with GT segments under this area as void")
    progress: bool = Field(True, description="progress bar (only on a terminal)")

    @field_validator("scenarios")
    @classmethod
    def _known(cls, v: list[str]) -> list[str]:
        from pvslam_plugins.datasets.synthetic.generator import SCENARIOS

        unknown = [s for s in v if s not in SCENARIOS]
        if unknown:
            raise ValueError(f"unknown synthetic scenarios {unknown}; available: {', '.join(SCENARIOS)}")
        return v

    @field_validator("val_seeds")
    @classmethod
    def _held_out(cls, v: list[int], info) -> list[int]:
        common = set(v) & (set(info.data.get("train_seeds", [])) | set(info.data.get("domain_seeds", [])))
        if common:
            raise ValueError(f"val_seeds {sorted(common)} are also training seeds; validation seeds must be held out")
        return v


def schedule_progress(cfg: TrainConfig, it: int, elapsed_s: float) -> float:
    """Fraction of the run done: iterations or the time budget, whichever is further along.  On a shared machine
    the speed is unknown in advance; this way the learning rate always completes its decay before the run stops."""
    return max(it / cfg.iterations, elapsed_s / (60.0 * cfg.time_budget_min))


def lr_at(cfg: TrainConfig, it: int, progress: float) -> float:
    """Linear warm-up over ``warmup`` iterations, then a cosine decay over the schedule's progress."""
    if it < cfg.warmup:
        return cfg.lr * (0.1 + 0.9 * it / max(cfg.warmup, 1))
    start = cfg.warmup / cfg.iterations
    t = (progress - start) / max(1.0 - start, 1e-9)
    lo = cfg.final_lr_fraction
    return cfg.lr * (lo + (1 - lo) * 0.5 * (1 + math.cos(math.pi * min(max(t, 0.0), 1.0))))


def _samples(cfg: TrainConfig, cache: Path, seeds: list[int], frames: int, progress: bool, desc: str,
             domain: Optional[str] = None):
    from tqdm import tqdm

    from .data import load_samples

    out = []
    jobs = [(s, seed) for seed in seeds for s in cfg.scenarios]
    for scen, seed in tqdm(jobs, desc=desc, disable=not progress, leave=False):
        out += load_samples(cache, scen, seed, frames, cfg.width, cfg.height, domain)
    return out


def _batch(model, samples, order, pos, cfg, augment, cats, gen):
    from .data import panoptic_targets
    from .losses import IGNORE

    images, sems, targets = [], [], []
    for k in range(cfg.batch_size):
        s = samples[int(order[(pos + k) % len(order)])]
        img, ids = augment(s.image, s.ids, gen)
        sem, inst = panoptic_targets(ids, s.segments, cats, cfg.min_instance_area)
        images.append(img)
        sems.append(sem)
        targets.append(inst)
    batch, sizes, _ = model.preprocess(images)
    sem = torch.full((batch.shape[0], batch.shape[2], batch.shape[3]), IGNORE, dtype=torch.int64)
    for i, s in enumerate(sems):
        sem[i, : s.shape[0], : s.shape[1]] = s
    return batch, sizes, sem, targets


def _write_plot(csv_path: Path, png_path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = list(csv.DictReader(csv_path.open()))
    if not rows:
        return
    its = [int(r["iteration"]) for r in rows]
    fig = Figure(figsize=(9, 5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    win = max(1, len(rows) // 50)
    for key in ("loss",) + LOSS_TERMS:
        vals = torch.tensor([float(r[key]) for r in rows])
        smooth = torch.nn.functional.avg_pool1d(vals[None, None], win, 1, 0, count_include_pad=False)[0, 0]
        ax.plot(its[win - 1:], smooth.tolist(), label=key, lw=2.0 if key == "loss" else 1.0)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel(f"loss (moving mean of {win})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(png_path, dpi=100)


class PanopticFPNLoop(TrainingLoop):
    """The shared loop with this trainer's batches (one permutation of the frames per epoch, drawn from a generator
    seeded by the epoch, so a resumed run sees the same order), schedule and loss terms."""

    counter = "iteration"
    log_fields = ["iteration", "elapsed_s", "lr", "loss", *LOSS_TERMS]
    desc = "train panoptic_fpn"

    def __init__(self, cfg: TrainConfig, out: Path, model, cats, train: list, resume: bool, opt, gen) -> None:
        from .data import Augment

        super().__init__(cfg, out, model, opt, gen, resume, cfg.iterations)
        self.grad_clip, self.checkpoint_every = cfg.grad_clip, cfg.checkpoint_every
        self.cats, self.train = cats, train
        self.augment = Augment(scale=tuple(cfg.scale), crop=tuple(cfg.crop) if cfg.crop else None)
        self.epoch_len = max(1, len(train) // cfg.batch_size)
        self.order, self.order_epoch = None, -1
        model.train()

    def stop_reason(self) -> Optional[str]:
        if schedule_progress(self.cfg, self.step, self.elapsed) < 1.0:
            return None
        return "iterations" if self.step >= self.cfg.iterations else "time budget"

    def learning_rate(self) -> float:
        return lr_at(self.cfg, self.step, schedule_progress(self.cfg, self.step, self.elapsed))

    def loss(self) -> tuple[torch.Tensor, dict]:
        from .losses import panoptic_fpn_losses

        cfg, it = self.cfg, self.step
        epoch = it // self.epoch_len
        if epoch != self.order_epoch:
            self.order = torch.randperm(len(self.train), generator=torch.Generator().manual_seed(cfg.seed + epoch))
            self.order_epoch = epoch
        batch, sizes, sem, targets = _batch(self.model, self.train, self.order, (it % self.epoch_len) * cfg.batch_size,
                                            cfg, self.augment, self.cats, self.generator)
        losses = panoptic_fpn_losses(self.model, batch, sizes, sem, targets, generator=self.generator)
        loss = sum(losses.values())
        return loss, {"loss": float(loss.detach()), **{k: float(v.detach()) for k, v in losses.items()}}

    def log_row(self, values: dict, lr: float) -> dict:
        return {"iteration": self.step, "elapsed_s": f"{self.elapsed:.1f}", "lr": f"{lr:.3g}",
                **{k: f"{v:.5f}" for k, v in values.items()}}

    def postfix(self, values: dict) -> dict:
        return {"loss": f"{values['loss']:.3f}", "sem": f"{values['loss_sem_seg']:.3f}",
                "min": f"{self.elapsed / 60:.0f}"}


def run(cfg: TrainConfig, out: Path, resume: bool) -> dict:
    """The registered trainer: train, checkpoint, evaluate; returns the summary (saved as summary.json)."""
    from .checkpoint import save_checkpoint
    from .config import preset
    from .data import synthetic_category_set
    from .model import PanopticFPN

    out, cache = prepare_run(cfg, out)
    cats = synthetic_category_set()
    model = PanopticFPN(preset("reduced"), cats)
    if cfg.init_weights is not None:
        from .checkpoint import load_weights

        load_weights(model, cfg.init_weights, strict=True)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    gen = torch.Generator().manual_seed(cfg.seed)
    t_data = time.perf_counter()
    train = _samples(cfg, cache, cfg.train_seeds, cfg.frames_per_sequence, cfg.progress, "render train frames")
    if cfg.domain_seeds:
        train += _samples(cfg, cache, cfg.domain_seeds, cfg.frames_per_sequence, cfg.progress,
                          "render randomised train frames", TRAINING_DOMAIN)
    val = _samples(cfg, cache, cfg.val_seeds, cfg.val_frames_per_sequence, cfg.progress, "render val frames")
    data_s = time.perf_counter() - t_data
    loop = PanopticFPNLoop(cfg, out, model, cats, train, resume, opt, gen)
    stopped = loop.run()
    csv_path = out / loop.log_file
    _write_plot(csv_path, out / "loss.png")
    model.eval()
    save_checkpoint(model, out / "model_final.pth", extra={"iterations": loop.step, "train_minutes": loop.elapsed / 60})
    res = _evaluate(model, val, cfg, out)
    rows = list(csv.DictReader(csv_path.open()))
    first = rows[: max(1, len(rows) // 20)]
    final = rows[-max(1, len(rows) // 20):]

    def mean(rs, key):
        return sum(float(r[key]) for r in rs) / max(len(rs), 1)

    p = res["pq"]
    return {
        "iterations": loop.step, "stopped_by": stopped, "train_minutes": round(loop.elapsed / 60, 2),
        "data_minutes": round(data_s / 60, 2), "train_frames": len(train), "val_frames": len(val),
        "loss_first_5pct": round(mean(first, "loss"), 4) if rows else None,
        "loss_last_5pct": round(mean(final, "loss"), 4) if rows else None,
        "pq": round(p["pq"], 4), "sq": round(p["sq"], 4), "rq": round(p["rq"], 4),
        "pq_things": round(p["things"]["pq"], 4), "pq_stuff": round(p["stuff"]["pq"], 4),
        "pq_min_area": round(res["pq_min_area"]["pq"], 4) if "pq_min_area" in res else None,
        "val_seconds_per_frame": round(res["seconds_per_frame"], 4),
        "checkpoint": str(out / "model_final.pth"),
    }


def _evaluate(model, val: list, cfg: TrainConfig, out: Path) -> dict:
    """PQ/SQ/RQ on the validation frames, written as ``eval.json`` and ``eval.md``."""
    from .evaluate import evaluate, format_table

    res = evaluate(model, val, cfg.eval_min_gt_area)
    (out / "eval.json").write_text(json.dumps(res, indent=1, default=float))
    table = format_table(res)
    if "pq_min_area" in res:
        table += (f"\n\nWith ground-truth segments under {res['min_gt_area']} px as void:\n\n"
                  + format_table({"pq": res["pq_min_area"]}))
    (out / "eval.md").write_text(table + "\n")
    return res
