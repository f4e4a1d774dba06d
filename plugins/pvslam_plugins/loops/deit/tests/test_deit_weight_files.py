"""loop.pca_file and DeiT checkpoints through the shared loader: a file torch refuses, a Git LFS pointer or a
file that is no torch file is one error line naming it (the CLI's ``pvslam: error:``), not torch's traceback."""
from __future__ import annotations

import os

import pytest
import torch

from pvslam_plugins.loops.deit.checkpoint import CheckpointError, load_checkpoint
from pvslam_plugins.loops.deit.pca import PCAWhitening


class _Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.fixture
def files(tmp_path):
    good = tmp_path / "pca.pt"
    PCAWhitening.fit(torch.randn(40, 6, generator=torch.Generator().manual_seed(0)), dim=3).save(good)
    evil = tmp_path / "evil.pt"
    torch.save({"format": "pvslam.pca", "pca": {"mean": torch.zeros(6)}, "x": _Payload(tmp_path / "ran")}, evil)
    lfs = tmp_path / "lfs.pt"
    lfs.write_text("version https://git-lfs.github.com/spec/v1\noid sha256:0c0e\nsize 7762185\n")
    text = tmp_path / "text.pt"
    text.write_text("hello\n")
    broken = tmp_path / "broken.pt"
    torch.save({"pca": {"mean": torch.zeros(6), "components": "x", "eigenvalues": None}}, broken)
    return {"good": good, "evil": evil, "lfs": lfs, "text": text, "broken": broken}


def test_pca_file_errors_are_one_line(files, tmp_path):
    assert PCAWhitening.load(files["good"]).out_dim == 3
    for kind, want in (("evil", "refused"), ("lfs", "Git LFS pointer, not the weights: run `git lfs pull`"),
                       ("text", "not a readable torch file"), ("broken", "the 'pca' entry cannot be used")):
        with pytest.raises(ValueError) as ei:
            PCAWhitening.load(files[kind])
        msg = str(ei.value)
        assert "\n" not in msg and str(files[kind]) in msg and want in msg, msg
    assert not (tmp_path / "ran").exists()


def test_deit_checkpoint_lfs_pointer_and_refusal(files, tmp_path):
    with pytest.raises(CheckpointError, match="Git LFS pointer, not the weights: run `git lfs pull`"):
        load_checkpoint(files["lfs"])
    with pytest.raises(CheckpointError, match="refused") as ei:
        load_checkpoint(files["evil"])
    assert "\n" not in str(ei.value) and not (tmp_path / "ran").exists()
