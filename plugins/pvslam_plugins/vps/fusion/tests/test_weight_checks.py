"""Fusion weights: the shipped file is checked against its recorded sha256, and a file given as vps.weights that
torch refuses (or that is no torch file) is one error line naming it, not torch's traceback."""
from __future__ import annotations

import os
from types import SimpleNamespace

import pytest
import torch

from pvslam_plugins.vps.fusion import head as head_mod
from pvslam_plugins.vps.fusion.config import FusionConfig
from pvslam_plugins.vps.fusion.head import SHIPPED_FUSION, FusionHead


class _Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _head(config: FusionConfig) -> FusionHead:
    """A head whose segmenter is a stub with the shipped layer's channel count (no model is built)."""
    channels = torch.load(SHIPPED_FUSION, weights_only=True)["fusion_conv1.weight"].shape[0]
    return FusionHead(config, model=SimpleNamespace(cfg=SimpleNamespace(fpn=SimpleNamespace(out_channels=channels))))


def test_the_shipped_file_loads_and_a_changed_one_is_refused(tmp_path, monkeypatch):
    layer = _head(FusionConfig()).fusion
    assert torch.equal(layer.state_dict()["fusion_conv1.bias"],
                       torch.load(SHIPPED_FUSION, weights_only=True)["fusion_conv1.bias"])
    sd = torch.load(SHIPPED_FUSION, weights_only=True)
    zeroed = tmp_path / "fusion_reduced.pth"
    torch.save({k: torch.zeros_like(v) for k, v in sd.items()}, zeroed)  # loads fine, fuses nothing
    monkeypatch.setattr(head_mod, "SHIPPED_FUSION", zeroed)
    with pytest.raises(ValueError, match=r"vps fusion: the shipped file .*fusion_reduced\.pth is corrupt or was "
                                         r"replaced"):
        _head(FusionConfig()).fusion
    zeroed.write_text("not a torch file\n")  # the same for a shipped file that is no torch file at all
    with pytest.raises(ValueError, match="is corrupt or was replaced"):
        _head(FusionConfig()).fusion


def test_vps_weights_that_torch_refuses_or_cannot_read_are_one_line(tmp_path):
    evil = tmp_path / "evil.pth"
    sd = torch.load(SHIPPED_FUSION, weights_only=True)
    torch.save({**sd, "x": _Payload(tmp_path / "ran")}, evil)
    text = tmp_path / "text.pth"
    text.write_text("hello\n")
    other = tmp_path / "other.pth"
    torch.save({"w": torch.zeros(1)}, other)
    for f, want in ((evil, "refused"), (text, "not a readable torch file"), (other, "fusion_conv1.weight")):
        with pytest.raises(ValueError) as ei:
            _head(FusionConfig(weights=str(f))).fusion
        msg = str(ei.value)
        assert "\n" not in msg and str(f) in msg and want in msg and msg.startswith("vps fusion weights: "), msg
    assert not (tmp_path / "ran").exists()
