"""The shipped checkpoint is checked against its recorded sha256 (a zeroed or replaced file is refused, not loaded
silently), and a Git LFS pointer is named as such, not called unsafe."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.segmenters.panoptic_fpn import segmenter as seg_mod
from pvslam_plugins.segmenters.panoptic_fpn.checkpoint import CheckpointError, UnsafeCheckpoint
from pvslam_plugins.segmenters.panoptic_fpn.segmenter import SHIPPED_WEIGHTS, PanopticFPNSegmenterConfig, build_model

LFS = "version https://git-lfs.github.com/spec/v1\noid sha256:1d02f92e\nsize 8520508\n"


def test_a_zeroed_shipped_checkpoint_is_refused(tmp_path, monkeypatch):
    data = torch.load(SHIPPED_WEIGHTS, map_location="cpu", weights_only=True)
    data["state_dict"] = {k: torch.zeros_like(v) for k, v in data["state_dict"].items()}
    zeroed = tmp_path / "reduced_synthetic.pth"
    torch.save(data, zeroed)  # a valid file of the right layout: it would load and segment nothing
    monkeypatch.setattr(seg_mod, "SHIPPED_WEIGHTS", zeroed)
    monkeypatch.setitem(seg_mod.DEFAULT_WEIGHTS, "reduced", str(zeroed))
    with pytest.raises(CheckpointError, match=r"segmenter panoptic_fpn: the shipped file .*reduced_synthetic\.pth "
                                              r"is corrupt or was replaced: sha256 .*; reinstall pvslam"):
        build_model(PanopticFPNSegmenterConfig())


def test_a_git_lfs_pointer_is_named_not_called_unsafe(tmp_path, monkeypatch):
    for name in ("panFPN.pth", "model_final.pkl"):
        f = tmp_path / name
        f.write_text(LFS)
        with pytest.raises(CheckpointError, match="Git LFS pointer, not the weights: run `git lfs pull`") as ei:
            build_model(PanopticFPNSegmenterConfig(weights=str(f)))
        assert not isinstance(ei.value, UnsafeCheckpoint) and str(f) in str(ei.value)
    shipped = tmp_path / "reduced_synthetic.pth"  # a checkout without `git lfs pull`
    shipped.write_text(LFS)
    monkeypatch.setattr(seg_mod, "SHIPPED_WEIGHTS", shipped)
    monkeypatch.setitem(seg_mod.DEFAULT_WEIGHTS, "reduced", str(shipped))
    with pytest.raises(CheckpointError, match="Git LFS pointer, not the weights: run `git lfs pull`"):
        build_model(PanopticFPNSegmenterConfig())
