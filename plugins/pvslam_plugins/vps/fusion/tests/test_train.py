"""The fusion trainer trains fusion_conv1 only and writes a checkpoint the head loads (tiny synthetic pairs)."""
from __future__ import annotations

import json

import numpy as np
import torch

from pvslam_core.types import Segment
from pvslam_plugins.vps.fusion import data as fusion_data
from pvslam_plugins.vps.fusion.layer import FeatureFusion, load_fusion
from pvslam_plugins.vps.fusion.train import TrainConfig, run

H, W = 64, 96


def _pair(shift: int) -> fusion_data.Pair:
    def image(x):
        img = np.zeros((H, W, 3), np.uint8)
        img[: H // 3] = (110, 160, 230)
        img[H // 3:] = (90, 90, 95)
        img[30:50, x:x + 24] = (200, 30, 30)
        return torch.from_numpy(img.transpose(2, 0, 1).copy())

    ids = np.full((H, W), 6000, np.int64)  # sky (category 6)
    ids[H // 3:] = 1000  # road (category 1)
    ids[30:50, 20 + shift:44 + shift] = 11001  # a car (category 11)
    segs = [Segment(6000, 6, False), Segment(1000, 1, False), Segment(11001, 11, True)]
    flow = torch.zeros(2, H // 8, W // 8)
    flow[0] = float(shift)
    return fusion_data.Pair(image(20), image(20 + shift), torch.from_numpy(ids), segs, flow,
                            torch.full((H // 8, W // 8), 5.0), f"tiny/{shift}")


def test_trainer_updates_only_the_fusion_layer(tmp_path, monkeypatch):
    monkeypatch.setattr(fusion_data, "load_pairs", lambda cache, scen, seed, n, *a, **k: [_pair(2 + seed % 3)])
    cfg = TrainConfig(scenarios=["moving_vehicles"], train_seeds=[10, 11], val_seeds=[100], iterations=4,
                      pairs_per_sequence=1, val_pairs_per_sequence=1, progress=False, lr=1e-2)
    summary = run(cfg, tmp_path, False)
    assert summary["iterations"] == 4 and summary["train_pairs"] == 2
    layer = load_fusion(FeatureFusion(64), tmp_path / "fusion_final.pth")  # strict: only fusion_conv1.*
    ident = FeatureFusion(64)
    assert not torch.allclose(layer.fusion_conv1.weight, ident.fusion_conv1.weight)  # it trained
    ev = json.loads((tmp_path / "eval.json").read_text())
    # before training the fused decode is the plain one exactly (identity initialisation)
    assert ev["identity_init"]["pq_fused"] == ev["identity_init"]["pq_plain"]


def test_domain_seeds_add_restyled_training_pairs(tmp_path, monkeypatch):
    """``domain_seeds``: pairs of the generator's training look join the plain ones; validation stays plain."""
    calls = []

    def fake(cache, scen, seed, n, *a, domain=None):
        calls.append((seed, domain))
        return [_pair(2 + seed % 3)]

    monkeypatch.setattr(fusion_data, "load_pairs", fake)
    cfg = TrainConfig(scenarios=["moving_vehicles"], train_seeds=[10], domain_seeds=[15, 16], val_seeds=[100],
                      iterations=2, pairs_per_sequence=1, val_pairs_per_sequence=1, progress=False)
    summary = run(cfg, tmp_path, False)
    assert summary["train_pairs"] == 3
    assert calls == [(10, None), (15, "train"), (16, "train"), (100, None)]


def test_restyled_pairs_are_the_same_scene_in_another_look(tmp_path):
    plain = fusion_data.load_pairs(tmp_path, "moving_vehicles", 15, 1, 96, 72)
    styled = fusion_data.load_pairs(tmp_path, "moving_vehicles", 15, 1, 96, 72, domain="train")
    again = fusion_data.load_pairs(tmp_path, "moving_vehicles", 15, 1, 96, 72, domain="train")  # from the cache
    assert len(list(tmp_path.glob("*.npz"))) == 2 and styled[0].name.endswith("/train")
    assert not torch.equal(plain[0].image1, styled[0].image1)
    assert torch.equal(styled[0].image1, again[0].image1) and torch.equal(styled[0].ids1, again[0].ids1)


def test_a_cache_written_by_another_run_meanwhile_is_no_collision(tmp_path, monkeypatch):
    """Another training run caches the same pairs between this run's write and its replace (a shared cache)."""
    real_save, other = np.savez_compressed, []

    def save_then_the_other_run(*args, **kwargs):
        real_save(*args, **kwargs)
        if not other:
            other.append(None)
            other[0] = fusion_data.load_pairs(tmp_path, "moving_vehicles", 15, 1, 96, 72)

    monkeypatch.setattr(fusion_data.np, "savez_compressed", save_then_the_other_run)
    mine = fusion_data.load_pairs(tmp_path, "moving_vehicles", 15, 1, 96, 72)
    assert torch.equal(mine[0].image1, other[0][0].image1)
    assert [f.name for f in tmp_path.iterdir()] == ["pairs-moving_vehicles-seed15-n1-96x72.npz"]
