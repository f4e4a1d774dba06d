"""``pvslam train vps --plugin fusion``: train only ``fusion_conv1`` (as PVO), on top of the frozen shipped
PanopticFPN, on consecutive frames of the generator's scenarios with moving vehicles.

    pvslam train vps --plugin fusion --out runs/fusion            # defaults below (~25 min on this CPU)

The segmenter is frozen, so each pair's features (frame t, and frame t-1 warped into t) are computed once and
kept (float16); an iteration runs only the fusion layer and the heads.  The loss is PanopticFPN's own (semantic,
RPN, box, mask) on frame t's exact labels, computed on the fused pyramid: the layer learns what of the previous
frame helps the decode.  Validation on held-out seeds: PQ of the fused decode against the plain one.  Written
into the output folder: ``last.pt`` (resumable state, every 50 iterations; ``--resume`` continues from it),
``loss.csv``, ``fusion_final.pth`` (``fusion_conv1.weight/bias`` only; the head loads it with ``vps.weights``),
``eval.json``.
"""
from __future__ import annotations

import csv
import json
import math
import time
from pathlib import Path
from typing import Optional

import torch
from pydantic import Field

from pvslam_core.config_base import PluginConfig
from pvslam_core.training import TrainingLoop, prepare_run

__all__ = ["TrainConfig", "run"]

LOSS_TERMS = ("loss_sem_seg", "loss_rpn_cls", "loss_rpn_loc", "loss_cls", "loss_box_reg", "loss_mask")


class TrainConfig(PluginConfig):
    scenarios: list[str] = Field(["moving_vehicles", "busy_street"], description="generator scenarios")
    train_seeds: list[int] = Field([10, 11, 12, 13, 14], description="generator seeds of the training pairs (apart "
                                   "from the segmenter's training and validation seeds)")
    val_seeds: list[int] = Field([100], description="held-out seeds for validation")
    domain_seeds: list[int] = Field([], description="more training seeds, rendered in the generator's training look "
                                    "(dataset.domain = \"train\"), so that the layer does not learn one look")
    pairs_per_sequence: int = Field(10, ge=1, description="consecutive-frame pairs per training (scenario, seed)")
    val_pairs_per_sequence: int = Field(6, ge=1, description="pairs per validation (scenario, seed)")
    segmenter_weights: Optional[str] = Field(None, description="frozen segmenter (default: the shipped reduced)")
    iterations: int = Field(1500, ge=1, description="iterations at most (see time_budget_min)")
    batch_size: int = Field(2, ge=1, description="pairs per iteration")
    lr: float = Field(3e-4, gt=0, description="peak learning rate (AdamW, cosine decay)")
    final_lr_fraction: float = Field(0.05, ge=0, le=1, description="cosine decay ends at lr * this")
    time_budget_min: float = Field(20.0, gt=0, description="training minutes at most (rendering comes on top)")
    z_order: bool = Field(True, description="warp the previous features with depth z-ordering (as the head does)")
    threads: int = Field(1, ge=0, description="torch threads (0 = torch's default)")
    seed: int = Field(0, description="seed of the batches and the loss sampling")
    data_cache: Optional[str] = Field(None, description="folder of the rendered-pair cache (default: OUT/data)")
    progress: bool = Field(True, description="print the loss every 50 iterations")


def _features(model, pairs, z_order: bool):
    """Per pair: current and warped-previous pyramids (float16, batch of 1) and the targets of frame t."""
    from pvslam_plugins.segmenters.panoptic_fpn.data import panoptic_targets

    from .feature_warp import warp_pyramid

    out = []
    with torch.no_grad():
        for p in pairs:
            pyr = model.extract([p.image0, p.image1])
            H, W = p.image1.shape[-2:]
            prev = {k: v[0:1] for k, v in pyr.levels.items()}
            cur = {k: v[1:2] for k, v in pyr.levels.items()}
            warped = warp_pyramid(prev, pyr.strides, p.flow[None], (H, W), pyr.image_sizes[0],
                                  p.depth0[None] if z_order else None)
            sem, inst = panoptic_targets(p.ids1, p.segments1, model.categories, 8)
            out.append(({k: v.half() for k, v in cur.items()}, {k: v.half() for k, v in warped.items()}, sem, inst))
    return out


def _batch(model, feats, idx):
    from pvslam_plugins.segmenters.panoptic_fpn.losses import IGNORE

    cur = {k: torch.cat([feats[i][0][k] for i in idx]).float() for k in feats[0][0]}
    warped = {k: torch.cat([feats[i][1][k] for i in idx]).float() for k in feats[0][1]}
    hp, wp = cur["p2"].shape[-2] * 4, cur["p2"].shape[-1] * 4
    sem = torch.full((len(idx), hp, wp), IGNORE, dtype=torch.int64)
    for b, i in enumerate(idx):
        s = feats[i][2]
        sem[b, : s.shape[0], : s.shape[1]] = s
    return cur, warped, sem, [feats[i][3] for i in idx]


def _pq(model, layer, pairs, feats) -> dict:
    from pvslam_core.evaluation.panoptic import pq
    from pvslam_core.types import PanopticSegmentation

    plain, fused = [], []
    with torch.no_grad():
        for p, (cur, warped, _, _) in zip(pairs, feats):
            H, W = p.image1.shape[-2:]
            c = {k: v.float() for k, v in cur.items()}
            pyr = model.pyramid_for(c, (H, W))
            plain.append(model.decode(pyr)[0].to_panoptic(False))
            f = {k: layer(v, warped[k].float()) for k, v in c.items()}
            fused.append(model.decode(pyr.replace(f))[0].to_panoptic(False))
    gts = [PanopticSegmentation(p.ids1, p.segments1) for p in pairs]
    cats = list(model.categories.categories)
    a, b = pq(plain, gts, cats), pq(fused, gts, cats)
    return {"pq_plain": a["all"]["pq"], "pq_fused": b["all"]["pq"], "pq_things_plain": a["things"]["pq"],
            "pq_things_fused": b["things"]["pq"]}


class FusionLoop(TrainingLoop):
    """The shared loop over the fusion layer only (the segmenter is frozen): random pairs of precomputed features,
    PanopticFPN's losses on the fused pyramid, a cosine learning rate over the run's progress (no warm-up)."""

    counter = "iteration"
    log_fields = ["iteration", "elapsed_s", "lr", "loss", *LOSS_TERMS]
    checkpoint_every = 50
    desc = "train fusion"

    def __init__(self, cfg: TrainConfig, out: Path, model, layer, train: list, feats: list, resume: bool) -> None:
        opt = torch.optim.AdamW(layer.parameters(), lr=cfg.lr, weight_decay=0.0)
        super().__init__(cfg, out, layer, opt, torch.Generator().manual_seed(cfg.seed), resume, cfg.iterations)
        self.segmenter, self.train, self.feats = model, train, feats
        self.bar_options = {"disable": True}  # `progress` prints a line every checkpoint instead

    def _progress(self) -> float:
        return max(self.step / self.cfg.iterations, self.elapsed / (60 * self.cfg.time_budget_min))

    def stop_reason(self) -> Optional[str]:
        if self.step >= self.cfg.iterations:
            return "iterations"
        return "time budget" if self._progress() >= 1.0 else None

    def learning_rate(self) -> float:
        cfg = self.cfg
        return cfg.lr * (cfg.final_lr_fraction + (1 - cfg.final_lr_fraction) * 0.5
                         * (1 + math.cos(math.pi * self._progress())))

    def loss(self) -> tuple[torch.Tensor, dict]:
        from pvslam_plugins.segmenters.panoptic_fpn.losses import pyramid_losses

        model = self.segmenter
        idx = torch.randint(len(self.feats), (self.cfg.batch_size,), generator=self.generator).tolist()
        cur, warped, sem, targets = _batch(model, self.feats, idx)
        H, W = self.train[idx[0]].image1.shape[-2:]
        pyr = model.pyramid_for({k: v[0] for k, v in cur.items()}, (H, W))
        pyr = type(pyr)({k: self.model(v, warped[k]) for k, v in cur.items()}, pyr.strides,
                        pyr.image_sizes * len(idx), pyr.output_sizes * len(idx))
        losses = pyramid_losses(model, pyr, sem, targets, generator=self.generator)
        loss = sum(losses.values())
        return loss, {"loss": float(loss.detach()), **{k: float(v.detach()) for k, v in losses.items()}}

    def log_row(self, values: dict, lr: float) -> dict:
        return {"iteration": self.step, "elapsed_s": round(self.elapsed, 1), "lr": lr, **values}

    def on_checkpoint(self) -> None:
        if self.cfg.progress:
            rows = list(csv.DictReader((self.out / self.log_file).open()))[-self.checkpoint_every:]
            print(f"it {self.step} loss {sum(float(r['loss']) for r in rows) / len(rows):.4f} "
                  f"lr {float(rows[-1]['lr']):.2g} {self.elapsed / 60:.1f} min", flush=True)


def run(cfg: TrainConfig, out: Path, resume: bool) -> dict:
    """The registered trainer (see the module docstring); returns the summary."""
    from pvslam_plugins.segmenters.panoptic_fpn.segmenter import PanopticFPNSegmenterConfig, build_model

    from .data import load_pairs
    from .layer import FeatureFusion

    out, cache = prepare_run(cfg, out)
    model = build_model(PanopticFPNSegmenterConfig(weights=cfg.segmenter_weights))
    for q in model.parameters():
        q.requires_grad_(False)
    layer = FeatureFusion(model.cfg.fpn.out_channels)
    t0 = time.perf_counter()
    looks = [(seed, None) for seed in cfg.train_seeds] + [(seed, "train") for seed in cfg.domain_seeds]
    train = [p for seed, look in looks for s in cfg.scenarios
             for p in load_pairs(cache, s, seed, cfg.pairs_per_sequence, domain=look)]
    val = [p for seed in cfg.val_seeds for s in cfg.scenarios
           for p in load_pairs(cache, s, seed, cfg.val_pairs_per_sequence)]
    tf, vf = _features(model, train, cfg.z_order), _features(model, val, cfg.z_order)
    data_s = time.perf_counter() - t0
    loop = FusionLoop(cfg, out, model, layer, train, tf, resume)
    before = _pq(model, layer, val, vf)
    model.train()  # heads in training mode: the losses sample proposals; GroupNorm has no running statistics
    stopped = loop.run()
    model.eval()
    layer.eval()
    torch.save(layer.state_dict(), out / "fusion_final.pth")
    after = _pq(model, layer, val, vf)
    (out / "eval.json").write_text(json.dumps({"identity_init": before, "trained": after}, indent=1))
    losses = [float(r["loss"]) for r in csv.DictReader((out / loop.log_file).open())]
    k = max(1, len(losses) // 20)
    return {"iterations": loop.step, "stopped_by": stopped, "train_minutes": round(loop.elapsed / 60, 2),
            "data_minutes": round(data_s / 60, 2), "train_pairs": len(train), "val_pairs": len(val),
            "loss_first_5pct": sum(losses[:k]) / k if losses else None,
            "loss_last_5pct": sum(losses[-k:]) / k if losses else None,
            "val_identity_init": before, "val_trained": after, "checkpoint": str(out / "fusion_final.pth")}
