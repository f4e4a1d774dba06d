"""``pvslam train loop --plugin deit``: a small DeiT trained contrastively for place recognition on synthetic data.

No pretrained DeiT weights can be downloaded here, so the descriptor of eq. 12 is learned from the built-in
generator: the same architecture (timm/DeiT parameter names, plain or distilled) at a small width (embed 192,
3 heads), trained from scratch on frames of several generated worlds (:mod:`.train_data`).

Losses, on L2-normalised final-norm tokens of a batch drawn from one world:

* supervised contrastive (SupCon, temperature ``temperature``) on the class token: every ground-truth positive of
  an anchor against its negatives (gray-zone pairs ignored);
* a margin term ``relu(s_neg - neg_margin)^2 + relu(pos_margin - s_pos)^2``: the detector thresholds cosine
  similarities with one global threshold, so scores must be separated in absolute terms, not only ranked;
* distilled variant, DeiT-style (``loss = (L_cls + L_dist) / 2``): the distillation token learns the teacher's
  similarity structure (KL between batch-row softmaxes), the teacher being the classical global descriptor - as
  DeiT distils a convnet's inductive bias into a ViT, this distils a hand-made descriptor's invariances.

Seeds are explicit and disjoint (``train_seeds``, ``val_seeds``; the test seeds used by the ablation are never
read here).  Validation (every ``val_every`` steps) measures recall@1 and the recall at the threshold that gives
precision 1.00 on the validation seeds (:mod:`.place_eval`); the best checkpoint is kept.  At the end the best
weights get a PCA fitted on training descriptors, the token and PCA choice and the threshold are calibrated on the
validation seeds, and ``model.pt`` (project checkpoint format, with the PCA and these settings) is written.

Outputs in ``out_dir``: ``state.pt`` (resumable training state), ``train_log.csv`` (per step: loss terms, lr,
seconds), ``val_log.csv``, ``curves.png``, ``best.pt``, ``model.pt``, ``summary.json`` (by the core).
"""
from __future__ import annotations

import csv
import math
import random
import time
from pathlib import Path
from typing import Literal, Optional

import torch
import torch.nn.functional as F
from pydantic import Field

from pvslam_core.config_base import PluginConfig
from pvslam_core.training import TrainingLoop, prepare_run

from .checkpoint import load_checkpoint, save_checkpoint
from .descriptor import select_tokens
from .pca import PCAWhitening
from .place_eval import calibrate, top_one
from .preprocess import IMAGENET_MEAN, IMAGENET_STD
from .train_data import Augment, PlaceSequence, load_sequences
from .vit import ViTConfig, VisionTransformer, build_vit


class DeitTrainConfig(PluginConfig):
    # --- data --------------------------------------------------------------------------------------------------
    scenarios: list[str] = Field(["driving_loop", "indoor_handheld"], description="generator scenarios to train on")
    train_seeds: list[int] = Field([101, 102, 103, 104, 105, 106, 107, 108],
                                   description="generator seeds (worlds) used for training, per scenario")
    val_seeds: list[int] = Field([201, 202], description="held-out generator seeds for validation and threshold "
                                 "calibration, per scenario (keep them apart from any test seeds)")
    num_frames: Optional[int] = Field(None, description="frames per sequence (None: the scenario's default)")
    hard_k: int = Field(8, ge=1, description="hard negatives remembered per frame (classical-descriptor look-alikes)")
    neg_factor: float = Field(2.0, gt=1.0, description="negatives: centres more than this x the revisit radius apart "
                              "(or axes more than neg_angle_deg apart); pairs between positive and negative are ignored")
    neg_angle_deg: float = Field(35.0, gt=0, le=180, description="negatives: optical axes more than this apart")
    data_cache: Optional[str] = Field(None, description="folder for the frames resized to the model input (reused "
                                      "by later runs and resumes); None: <out>/data")
    # --- model -------------------------------------------------------------------------------------------------
    init: Optional[str] = Field(None, description="start from this project checkpoint (fine-tuning; its "
                                "architecture replaces embed_dim/depth/num_heads/input_size)")
    variant: Literal["base", "distilled"] = Field("distilled", description="plain DeiT or DeiT-distilled")
    embed_dim: int = Field(192, ge=16, description="token width (DeiT-Tiny's; DeiT-base has 768)")
    depth: int = Field(4, ge=1, description="transformer blocks")
    num_heads: int = Field(3, ge=1, description="attention heads per block (embed_dim must be a multiple)")
    input_size: int = Field(112, ge=16, description="full-frame token budget of (input_size/16)^2 patches, aspect "
                            "ratio kept (96x128 pixels for 320x240 frames)")
    drop_path: float = Field(0.05, ge=0.0, lt=1.0, description="stochastic depth rate (regularisation)")
    # --- optimisation ------------------------------------------------------------------------------------------
    steps: int = Field(2000, ge=1, description="optimiser steps (the run also stops at max_minutes)")
    max_minutes: float = Field(45.0, gt=0, description="wall-clock budget of this invocation (resume continues)")
    anchors: int = Field(20, ge=2, description="anchor frames per batch (each with one positive)")
    hard: int = Field(10, ge=0, description="hard negatives per batch")
    revisit_prob: float = Field(0.5, ge=0, le=1, description="draw a positive from another pass when there is one")
    lr: float = Field(5e-4, gt=0, description="peak learning rate (AdamW, cosine decay)")
    weight_decay: float = Field(0.05, ge=0, description="AdamW weight decay")
    warmup: int = Field(100, ge=0, description="steps of linear learning-rate warm-up")
    temperature: float = Field(0.1, gt=0, description="temperature of the supervised contrastive loss")
    pos_margin: float = Field(0.75, ge=-1, le=1, description="margin loss: positives' cosine similarity should "
                              "exceed this (the detector uses one global threshold)")
    neg_margin: float = Field(0.35, ge=-1, le=1, description="margin loss: negatives' cosine similarity should "
                              "stay below this")
    margin_weight: float = Field(1.0, ge=0, description="weight of the margin loss against the contrastive one")
    kd_temperature: float = Field(0.05, gt=0, description="teacher softmax temperature (distilled variant)")
    seed: int = Field(0, description="seed of the initialisation, the batches and the augmentation")
    threads: int = Field(2, ge=1, description="torch CPU threads")
    # --- bookkeeping -------------------------------------------------------------------------------------------
    val_every: int = Field(250, ge=1, description="validate (and keep the best weights) every this many steps; at "
                           "checkpoints only")
    checkpoint_every: int = Field(50, ge=1, description="write the resumable state every this many steps")
    val_stride: int = Field(3, ge=1, description="validation: every n-th frame is a keyframe")
    exclude_recent: int = Field(20, ge=0, description="validation: temporal exclusion in keyframes (as the detector)")
    min_time_gap: float = Field(10.0, ge=0, description="validation: temporal exclusion in seconds (as the detector)")
    max_rotation_deg: Optional[float] = Field(60.0, description="validation: skip candidates whose ground-truth "
                                              "optical axes differ by more (the loop policy's orientation check)")
    progress: bool = Field(True, description="tqdm progress bar")


# ------------------------------------------------------------------------------------------------ pieces --
def make_model(cfg: DeitTrainConfig, input_hw: tuple[int, int]) -> VisionTransformer:
    vc = ViTConfig(img_size=input_hw, patch_size=16, embed_dim=cfg.embed_dim, depth=cfg.depth,
                   num_heads=cfg.num_heads, num_classes=0, distilled=cfg.variant == "distilled",
                   drop_path_rate=cfg.drop_path)
    return build_vit(vc)


def normalise(x: torch.Tensor) -> torch.Tensor:
    m = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    s = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (x - m) / s


def supcon(z: torch.Tensor, pos: torch.Tensor, neg: torch.Tensor, tau: float) -> torch.Tensor:
    """Supervised contrastive loss of unit descriptors ``z [B, d]`` with pair masks ``[B, B]`` (diagonal ignored)."""
    eye = torch.eye(len(z), dtype=torch.bool)
    pos, valid = pos & ~eye, (pos | neg) & ~eye
    rows = pos.any(1) & (neg & ~eye).any(1)
    if not rows.any():
        return z.sum() * 0.0
    logits = (z[rows] @ z.T) / tau
    logits = logits.masked_fill(~valid[rows], float("-inf"))
    log_prob = logits - torch.logsumexp(logits, dim=1, keepdim=True)
    p = pos[rows]
    return -(log_prob.masked_fill(~p, 0.0).sum(1) / p.sum(1)).mean()


def margin_loss(z: torch.Tensor, pos: torch.Tensor, neg: torch.Tensor, m_pos: float, m_neg: float) -> torch.Tensor:
    eye = torch.eye(len(z), dtype=torch.bool)
    s = z @ z.T
    lp = F.relu(m_pos - s[pos & ~eye]).pow(2)
    ln = F.relu(s[neg & ~eye] - m_neg).pow(2)
    return (lp.mean() if len(lp) else s.sum() * 0) + (ln.mean() if len(ln) else s.sum() * 0)


def distill_loss(z: torch.Tensor, teacher: torch.Tensor, tau: float, t_tau: float) -> torch.Tensor:
    """KL(teacher row softmax || student row softmax) over the batch, self excluded."""
    eye = torch.eye(len(z), dtype=torch.bool)
    # a large finite negative, not -inf: the KL term exp(t) * (t - s) of the diagonal must be 0, not nan
    s = (z @ z.T / tau).masked_fill(eye, -1e4)
    t = (teacher @ teacher.T / t_tau).masked_fill(eye, -1e4)
    return F.kl_div(F.log_softmax(s, 1), F.log_softmax(t, 1), log_target=True, reduction="batchmean")


def prefix_tokens(model: VisionTransformer, frames: torch.Tensor, batch: int = 64) -> torch.Tensor:
    """Final-norm prefix tokens ``[N, P, D]`` (cls, and dist) of uint8 frames at the model input size."""
    was = model.training
    model.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(frames), batch):
            t = model.forward_tokens(normalise(frames[i : i + batch].float() / 255.0))
            out.append(t[:, : model.num_prefix_tokens])
    model.train(was)
    return torch.cat(out)


def evaluate_tokens(tokens: list[torch.Tensor], seqs: list[PlaceSequence], cfg: DeitTrainConfig,
                    token: str = "cls", pca: Optional[PCAWhitening] = None) -> dict:
    """Calibrated validation metrics from each sequence's keyframe prefix tokens ``[K, P, D]`` (frames
    ``0, val_stride, ...``)."""
    results = []
    for t, s in zip(tokens, seqs):
        f = select_tokens(t, token, t.shape[1])
        if pca is not None:
            f = pca.transform(f)
        results.append(top_one(F.normalize(f, dim=1), s.labels.pos, s.timestamps, cfg.val_stride,
                               cfg.exclude_recent, cfg.min_time_gap, axes=s.axes,
                               max_rotation_deg=cfg.max_rotation_deg))
    return calibrate(results)


def evaluate(model: VisionTransformer, seqs: list[PlaceSequence], cfg: DeitTrainConfig) -> dict:
    return evaluate_tokens([prefix_tokens(model, s.frames[:: cfg.val_stride]) for s in seqs], seqs, cfg)


def classical_baseline(seqs: list[PlaceSequence], cfg: DeitTrainConfig) -> dict:
    """The same protocol on the classical global descriptor (retrieval only, no verification)."""
    return calibrate([top_one(s.teacher[:: cfg.val_stride], s.labels.pos, s.timestamps, cfg.val_stride,
                              cfg.exclude_recent, cfg.min_time_gap, axes=s.axes,
                              max_rotation_deg=cfg.max_rotation_deg) for s in seqs])


def lr_at(step: int, cfg: DeitTrainConfig) -> float:
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    prog = (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup)
    return cfg.lr * 0.5 * (1 + math.cos(math.pi * min(1.0, prog)))


def _sequence_roots(cfg: DeitTrainConfig, seeds: list[int]) -> list[Path]:
    from pvslam_plugins.datasets.synthetic.generator import generate

    return [Path(generate(sc, seed=s, num_frames=cfg.num_frames, progress=False))
            for s in seeds for sc in cfg.scenarios]


# -------------------------------------------------------------------------------------------------- run --
class DeitLoop(TrainingLoop):
    """The shared loop with this trainer's batches (one world per batch), losses, logs and validation (recall at
    precision 1.00 first, recall@1 breaking ties; the best validation score's weights are kept in ``best.pt``)."""

    state_file = "state.pt"
    log_file, log_fields = "train_log.csv", ["step", "loss", "contrastive", "margin", "distill", "lr", "seconds"]
    val_file = "val_log.csv"
    val_fields = ["step", "recall_at_1", "threshold", "precision", "recall", "best_wrong", "median_revisit"]
    grad_clip = 1.0
    bar_options = {"mininterval": 5}

    def __init__(self, cfg: DeitTrainConfig, out: Path, model: VisionTransformer, train: list[PlaceSequence],
                 val: list[PlaceSequence], resume: bool) -> None:
        opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        super().__init__(cfg, out, model, opt, torch.Generator().manual_seed(cfg.seed), resume, cfg.steps)
        self.checkpoint_every, self.desc = cfg.checkpoint_every, f"deit-{cfg.variant}"
        self.train, self.val = train, val
        self.best = float(self.resumed.get("best", -1.0))
        if self.resumed:
            print(f"resumed at step {self.step} (best validation score {self.best:.3f})")
        self.order = list(range(len(train)))
        self.aug = Augment()
        self.budget_end = time.time() + 60.0 * cfg.max_minutes
        model.train()

    def stop_reason(self) -> Optional[str]:
        if self.step >= self.cfg.steps:
            return "steps"
        return None if time.time() < self.budget_end else "time budget"

    def learning_rate(self) -> float:
        return lr_at(self.step, self.cfg)

    def loss(self) -> tuple[torch.Tensor, dict]:
        cfg, step, order = self.cfg, self.step, self.order
        seq = self.train[order[step % len(order)]]
        if step % len(order) == len(order) - 1:
            random.Random(cfg.seed + step).shuffle(order)
        idx = seq.sample(self.generator, cfg.anchors, cfg.hard, cfg.revisit_prob)
        x = normalise(self.aug(seq.frames[idx], self.generator))
        pos, neg = seq.labels.pos[idx][:, idx], seq.labels.neg[idx][:, idx]
        tokens = self.model.forward_tokens(x)
        z = F.normalize(tokens[:, 0], dim=1)
        l_con = supcon(z, pos, neg, cfg.temperature)
        l_mar = margin_loss(z, pos, neg, cfg.pos_margin, cfg.neg_margin)
        loss = l_con + cfg.margin_weight * l_mar
        l_kd = torch.zeros(())
        if cfg.variant == "distilled":
            zd = F.normalize(tokens[:, 1], dim=1)
            l_kd = distill_loss(zd, seq.teacher[idx], cfg.temperature, cfg.kd_temperature)
            loss = 0.5 * loss + 0.5 * l_kd
        return loss, {"loss": loss.item(), "contrastive": l_con.item(), "margin": l_mar.item(),
                      "distill": l_kd.item()}

    def log_row(self, values: dict, lr: float) -> dict:
        return {"step": self.step, **{k: f"{v:.5f}" for k, v in values.items()}, "lr": f"{lr:.3e}",
                "seconds": f"{self.elapsed:.1f}"}

    def postfix(self, values: dict) -> dict:
        return {"loss": f"{values['loss']:.3f}"}

    def checkpoint_due(self) -> bool:
        return self.step % self.cfg.checkpoint_every == 0 or self.step == self.cfg.steps

    def validation_due(self) -> bool:
        return self.checkpoint_due() and (self.step % self.cfg.val_every == 0 or self.step == self.cfg.steps)

    def final_validation(self, steps_run: int) -> bool:
        return steps_run > 0 and not self.checkpoint_due()

    def validate(self) -> dict:
        from tqdm import tqdm

        m = evaluate(self.model, self.val, self.cfg)
        # recall at precision 1.00 first, recall@1 breaks ties (nan without revisit queries counts as 0)
        score = float(torch.nan_to_num(torch.tensor(m["recall"] + 0.25 * m["recall_at_1"])))
        if score > self.best:
            self.best = score
            save_checkpoint(self.out / "best.pt", self.model, meta={"step": self.step, "val_score": score})
        tqdm.write(f"step {self.step}: val recall@1 {m['recall_at_1']:.3f}, recall {m['recall']:.3f} at threshold "
                   f"{m['threshold']:.3f} (precision 1.00; best wrong {m['best_wrong']:.3f})")
        return {"step": self.step, **{k: f"{m[k]:.4f}" for k in self.val_fields[1:]}}

    def extra_state(self) -> dict:
        return {"best": self.best, "config": self.cfg.model_dump()}


def _init_model(cfg: DeitTrainConfig, input_hw: tuple[int, int]) -> VisionTransformer:
    """A new model, or the ``init`` checkpoint's (fine-tuning: its architecture, this run's drop-path rate)."""
    model = make_model(cfg, input_hw)
    if cfg.init is None:
        return model
    init = load_checkpoint(cfg.init).model
    if init.config.variant != model.config.variant or tuple(init.config.img_size) != tuple(input_hw):
        raise ValueError(f"init {cfg.init}: a {init.config.variant} DeiT at {init.config.img_size}, but this run "
                         f"trains a {model.config.variant} one at {input_hw}")
    init.config.drop_path_rate = cfg.drop_path
    model = build_vit(init.config)
    model.load_state_dict(init.state_dict())
    return model


def run_training(cfg: DeitTrainConfig, out: Path, resume: bool) -> dict:
    """The registered trainer (see the module docstring); returns the summary."""
    overlap = set(cfg.train_seeds) & set(cfg.val_seeds)
    if overlap:
        raise ValueError(f"train_seeds and val_seeds share {sorted(overlap)}: validation must be held out")
    out, cache = prepare_run(cfg, out)
    t_load = time.time()
    train = load_sequences(_sequence_roots(cfg, cfg.train_seeds), cfg.input_size, cfg.hard_k, cache, cfg.neg_factor,
                           cfg.neg_angle_deg)
    val = load_sequences(_sequence_roots(cfg, cfg.val_seeds), cfg.input_size, cfg.hard_k, cache, cfg.neg_factor,
                         cfg.neg_angle_deg)
    input_hw = train[0].input_hw
    print(f"data: {len(train)} training sequences ({sum(map(len, train))} frames), {len(val)} validation "
          f"({sum(map(len, val))} frames), input {input_hw[0]}x{input_hw[1]}, loaded in {time.time() - t_load:.0f} s")
    torch.manual_seed(cfg.seed)  # again: the model's initialisation does not depend on what loading the data drew
    random.seed(cfg.seed)
    loop = DeitLoop(cfg, out, _init_model(cfg, input_hw), train, val, resume)
    loop.run()
    summary = {"steps": loop.step, "finished": loop.step >= cfg.steps, "minutes": round(loop.elapsed / 60, 1),
               "input": list(input_hw), "train_seeds": cfg.train_seeds, "val_seeds": cfg.val_seeds}
    plot_curves(out)
    if (out / "best.pt").is_file():
        summary.update(export(out, cfg, train, val))
    return summary


def export(out: Path, cfg: DeitTrainConfig, train: list[PlaceSequence], val: list[PlaceSequence]) -> dict:
    """Fit the PCA, pick token / PCA and the threshold on the validation seeds, write ``model.pt``."""
    ck = load_checkpoint(out / "best.pt")
    model = ck.model
    tokens = ["cls"] + (["dist", "mean"] if cfg.variant == "distilled" else [])
    fit_tokens = torch.cat([prefix_tokens(model, s.frames[:: 2 * cfg.val_stride]) for s in train])
    val_tokens = [prefix_tokens(model, s.frames[:: cfg.val_stride]) for s in val]
    results = {}
    for token in tokens:
        # PCA fitted on (a subsample of) the training frames' descriptors; not whitened (the training already
        # spread the descriptors; whitening re-weights the directions the loss did not ask for)
        fit = select_tokens(fit_tokens, token, fit_tokens.shape[1])
        pca = PCAWhitening.fit(fit, dim=min(128, fit.shape[1]), whiten=False)
        for name, p in (("none", None), ("fixed", pca)):
            results[(token, name)] = (evaluate_tokens(val_tokens, val, cfg, token, p), p)
    key = max(results, key=lambda k: tuple(float(torch.nan_to_num(torch.tensor(results[k][0][n])))
                                           for n in ("recall", "recall_at_1")))
    m, pca = results[key]
    descriptor = {"resize": "full_frame", "input_size": list(train[0].input_hw), "token": key[0], "pca": key[1],
                  "threshold": round(float(m["threshold"]), 4)}
    meta = {"trained_on": "pvslam synthetic generator", "scenarios": ",".join(cfg.scenarios),
            "train_seeds": ",".join(map(str, cfg.train_seeds)), "val_seeds": ",".join(map(str, cfg.val_seeds)),
            "val_recall": float(m["recall"]), "val_recall_at_1": float(m["recall_at_1"])}
    save_checkpoint(out / "model.pt", model, pca if key[1] == "fixed" else None, descriptor, meta)
    table = {f"{t}/{p}": {k: round(v, 4) if isinstance(v, float) else v for k, v in r[0].items()}
             for (t, p), r in results.items()}
    base = classical_baseline(val, cfg)
    return {"validation": table, "chosen": descriptor, "classical_validation": base,
            "model": str(out / "model.pt"), "model_mb": round((out / "model.pt").stat().st_size / 2**20, 2)}


def plot_curves(out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def read(p: Path) -> dict[str, list[float]]:
        with open(p) as fh:
            rows = list(csv.DictReader(fh))
        return {k: [float(r[k]) for r in rows] for k in (rows[0] if rows else {})}

    tr, va = read(out / "train_log.csv"), read(out / "val_log.csv")
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    if tr:
        k = 25  # running mean over k steps
        for name in ("loss", "contrastive", "margin", "distill"):
            v = torch.tensor(tr[name])
            if len(v) >= k and float(v.abs().sum()) > 0:
                ax[0].plot(tr["step"][k - 1 :], v.unfold(0, k, 1).mean(1).tolist(), label=name)
        ax[0].set_xlabel("step")
        ax[0].set_title(f"training loss (running mean of {k})")
        if ax[0].lines:
            ax[0].legend()
    if va:
        for name in ("recall_at_1", "recall", "threshold"):
            ax[1].plot(va["step"], va[name], marker="o", label=name)
        ax[1].set_xlabel("step")
        ax[1].set_title("validation (held-out seeds)")
        ax[1].legend()
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=100)
    plt.close(fig)
