"""Weights files the plugins load themselves: one torch loader and one shipped-file check for all of them, each
failure one line that names the file (``pvslam: error: ...``), never torch's traceback."""
from __future__ import annotations

import os

import pytest
import torch

from pvslam_core import weights as W
from pvslam_core.training import load_training_state

LFS = b"version https://git-lfs.github.com/spec/v1\noid sha256:4d7a\nsize 8519935\n"


class _Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.fixture
def bad_files(tmp_path):
    """An unsafe pickle (it would run code), a Git LFS pointer, a text file and a truncated torch file."""
    evil = tmp_path / "evil.pt"
    torch.save({"model": {"w": torch.zeros(1)}, "x": _Payload(tmp_path / "ran")}, evil)
    lfs = tmp_path / "lfs.pt"
    lfs.write_bytes(LFS)
    text = tmp_path / "notes.pt"
    text.write_text("hello\n")
    good = tmp_path / "good.pt"
    torch.save({"w": torch.ones(3)}, good)
    cut = tmp_path / "cut.pt"
    cut.write_bytes(good.read_bytes()[:100])
    return {"evil": evil, "lfs": lfs, "text": text, "cut": cut, "good": good}


def _one_line(exc: BaseException, path) -> str:
    msg = str(exc)
    assert "\n" not in msg and str(path) in msg, msg
    return msg


def test_load_torch_file_names_each_failure_in_one_line(bad_files, tmp_path):
    assert torch.equal(W.load_torch_file(bad_files["good"], "test")["w"], torch.ones(3))
    with pytest.raises(W.WeightsError) as ei:
        W.load_torch_file(bad_files["evil"], "test weights")
    msg = _one_line(ei.value, bad_files["evil"])
    assert msg.startswith("test weights: ") and "refused" in msg and "system" in msg
    assert not (tmp_path / "ran").exists()  # nothing ran
    with pytest.raises(W.WeightsError) as ei:
        W.load_torch_file(bad_files["lfs"], "test weights")
    assert "Git LFS pointer, not the weights: run `git lfs pull`" in _one_line(ei.value, bad_files["lfs"])
    for kind in ("text", "cut"):
        with pytest.raises(W.WeightsError) as ei:
            W.load_torch_file(bad_files[kind], "test weights")
        msg = _one_line(ei.value, bad_files[kind])
        assert "not a readable torch file" in msg and "refused" not in msg and "Weights only" not in msg
    with pytest.raises(ValueError, match="no such file"):
        W.load_torch_file(tmp_path / "nope.pt", "test", error=ValueError)


def test_check_shipped(tmp_path):
    f = tmp_path / "shipped.pth"
    f.write_bytes(b"the shipped bytes")
    import hashlib

    digest = hashlib.sha256(b"the shipped bytes").hexdigest()
    assert W.check_shipped(f, digest, "plug", "reinstall") == f
    f.write_bytes(b"the shipped bytez")
    with pytest.raises(W.WeightsError, match=r"plug: the shipped file .*shipped\.pth is corrupt or was replaced: "
                                             r".*; reinstall"):
        W.check_shipped(f, digest, "plug", "reinstall")
    f.write_bytes(LFS)
    with pytest.raises(ValueError, match="Git LFS pointer, not the weights: run `git lfs pull`; reinstall"):
        W.check_shipped(f, digest, "plug", "reinstall", error=ValueError)
    with pytest.raises(FileNotFoundError, match="missing; reinstall"):
        W.check_shipped(tmp_path / "gone.pth", digest, "plug", "reinstall")


class _Gen:
    def __init__(self):
        self.state = None

    def get_state(self):
        return {"seed": 1}

    def set_state(self, s):
        self.state = s


def test_train_resume_with_a_bad_state_file_is_one_error_line(bad_files, tmp_path):
    """``pvslam train ... --resume`` reads the run's state file: a refused, foreign or broken one is a ValueError
    (the CLI's ``pvslam: error:`` line), not torch's traceback."""
    from pvslam_core.training import save_training_state

    model = torch.nn.Linear(2, 2)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    for kind in ("evil", "lfs", "text", "cut", "good"):  # good: a torch file, but not a training state
        with pytest.raises(ValueError) as ei:
            load_training_state(bad_files[kind], model, opt, _Gen(), "step")
        assert "--resume" in _one_line(ei.value, bad_files[kind])
    assert not (tmp_path / "ran").exists()
    state = tmp_path / "state.pt"
    save_training_state(state, model, opt, _Gen(), "step", 7, 12.5)
    gen = _Gen()
    assert load_training_state(state, model, opt, gen, "step")[:2] == (7, 12.5) and gen.state == {"seed": 1}
    with pytest.raises(ValueError, match="does not fit this trainer"):
        load_training_state(state, torch.nn.Linear(3, 3), opt, _Gen(), "step")
