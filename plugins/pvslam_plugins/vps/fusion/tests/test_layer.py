"""PVO's fusion layer: key names and shapes (strict loading), identity initialisation."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.vps.fusion.layer import FeatureFusion, fusion_state_dict, load_fusion


def _pvo_like_checkpoint() -> dict:
    """A state dict laid out like PVO's panFPN.pth (checkpoints.md §3): detectron2 keys plus fusion_conv1
    [256, 512, 3, 3] / [256], under ``model``."""
    g = torch.Generator().manual_seed(0)
    return {"model": {
        "backbone.fpn_lateral2.weight": torch.randn(256, 256, 1, 1, generator=g),
        "sem_seg_head.predictor.weight": torch.randn(12, 128, 1, 1, generator=g),
        "fusion_conv1.weight": torch.randn(256, 512, 3, 3, generator=g),
        "fusion_conv1.bias": torch.randn(256, generator=g),
    }, "iteration": 270000}


def test_pvo_fusion_layer_loads_strictly(tmp_path):
    ckpt = _pvo_like_checkpoint()
    path = tmp_path / "panFPN.pth"
    torch.save(ckpt, path)
    layer = load_fusion(FeatureFusion(256), path)
    assert set(layer.state_dict()) == {"fusion_conv1.weight", "fusion_conv1.bias"}
    assert torch.equal(layer.fusion_conv1.weight, ckpt["model"]["fusion_conv1.weight"])
    assert torch.equal(layer.fusion_conv1.bias, ckpt["model"]["fusion_conv1.bias"])
    # the loaded layer computes conv2d(cat(current, warped)) with PVO's weights (current first)
    cur, warped = torch.randn(1, 256, 5, 6), torch.randn(1, 256, 5, 6)
    ref = torch.nn.functional.conv2d(torch.cat([cur, warped], 1), ckpt["model"]["fusion_conv1.weight"],
                                     ckpt["model"]["fusion_conv1.bias"], padding=1)
    assert torch.allclose(layer(cur, warped), ref, atol=1e-4)


def test_prefixed_keys_and_errors():
    sd = {"module." + k: v for k, v in _pvo_like_checkpoint()["model"].items()}
    assert set(fusion_state_dict(sd)) == {"fusion_conv1.weight", "fusion_conv1.bias"}
    with pytest.raises(ValueError, match=r"fusion_conv1.weight has shape \(256, 512, 3, 3\).*"
                                         r"expects \(64, 128, 3, 3\)"):
        load_fusion(FeatureFusion(64), sd)
    del sd["module.fusion_conv1.bias"]
    with pytest.raises(KeyError, match="fusion_conv1.bias"):
        load_fusion(FeatureFusion(256), sd)


def test_identity_initialisation_returns_the_current_features():
    layer = FeatureFusion(8)
    cur, warped = torch.randn(2, 8, 7, 9), torch.randn(2, 8, 7, 9)
    assert torch.allclose(layer(cur, warped), cur, atol=1e-6)
