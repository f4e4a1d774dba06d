"""``pvslam train``: the core loads the trainer's config (TOML + --set, validated) and calls the plugin's trainer."""
import json

import pytest
from pydantic import Field

from pvslam_core.config import ConfigError
from pvslam_core.config_base import PluginConfig
from pvslam_core.registry import PluginError, build_registry, hookimpl
from pvslam_core.training import Trainer, train


class ToyTrainConfig(PluginConfig):
    steps: int = Field(3, ge=1, description="optimisation steps")
    lr: float = Field(0.1, gt=0, description="learning rate")


def toy_run(cfg, out, resume):
    state = out / "state.json"
    done = json.loads(state.read_text())["step"] if (resume and state.is_file()) else 0
    for step in range(done, cfg.steps):
        state.write_text(json.dumps({"step": step + 1}))
    return {"steps_run": cfg.steps - done, "lr": cfg.lr}


class ToyPlugin:
    @hookimpl
    def register_loop_detectors(self, register):
        register("toy", lambda c, ctx: None, ToyTrainConfig, description="test-only",
                 trainer=Trainer(ToyTrainConfig, toy_run))


@pytest.fixture
def registry():
    return build_registry(extra_modules=(ToyPlugin(),))


def test_train_dispatch_config_and_resume(tmp_path, registry):
    cfg = tmp_path / "train.toml"
    cfg.write_text("steps = 5\n")
    out, summary = train("loop", "toy", cfg, ["lr=0.5"], tmp_path / "t", registry=registry)
    assert summary == {"steps_run": 5, "lr": 0.5}
    saved = json.loads((out / "train_config.json").read_text())
    assert saved["plugin"] == "toy" and saved["config"] == {"steps": 5, "lr": 0.5}
    assert json.loads((out / "summary.json").read_text())["steps_run"] == 5
    _, again = train("loop", "toy", cfg, ["steps=7"], out, resume=True, registry=registry)
    assert again["steps_run"] == 2  # continued from step 5
    assert again["lr"] == 0.5  # the saved config, not the trainer's default


def test_a_resume_continues_the_saved_config_and_names_what_it_changes(tmp_path, registry, caplog):
    out, _ = train("loop", "toy", None, ["lr=0.5", "steps=2"], tmp_path / "t", registry=registry)
    _, same = train("loop", "toy", None, None, out, resume=True, registry=registry)
    assert same == {"steps_run": 0, "lr": 0.5}  # no --set: exactly the run that was started
    assert not [r for r in caplog.records if "changed" in r.getMessage()]
    more = tmp_path / "more.toml"
    more.write_text("steps = 4\n")
    _, longer = train("loop", "toy", more, None, out, resume=True, registry=registry)
    assert longer == {"steps_run": 2, "lr": 0.5}
    assert json.loads((out / "train_config.json").read_text())["config"] == {"steps": 4, "lr": 0.5}
    assert any("steps changed from 2 to 4" in r.getMessage() for r in caplog.records)
    with pytest.raises(ConfigError, match="unknown key 'stepz'"):
        train("loop", "toy", None, ["stepz=5"], out, resume=True, registry=registry)


def test_train_errors(tmp_path, registry):
    bad = tmp_path / "bad.toml"
    bad.write_text("stepz = 5\n")
    with pytest.raises(ConfigError, match="unknown key 'stepz'.*allowed keys here: steps, lr"):
        train("loop", "toy", bad, registry=registry, out_dir=tmp_path / "x")
    with pytest.raises(PluginError, match="has no trainer; trainable plugins: .*loop toy"):
        train("frontend", "flow", registry=build_registry(extra_modules=(ToyPlugin(),)))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        train("loop", "toy", resume=True, out_dir=tmp_path / "missing", registry=registry)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="train_config.json not found"):
        train("loop", "toy", resume=True, out_dir=tmp_path / "empty", registry=registry)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "train_config.json").write_text(json.dumps({"interface": "segmenter", "plugin": "x",
                                                                      "config": {}}))
    with pytest.raises(ValueError, match="holds a run of segmenter --plugin x, not loop --plugin toy"):
        train("loop", "toy", resume=True, out_dir=tmp_path / "other", registry=registry)


def test_prepare_run_sets_threads_seed_and_cache(tmp_path):
    import types

    import torch

    from pvslam_core.training import prepare_run

    n = torch.get_num_threads()
    try:
        cfg = types.SimpleNamespace(threads=1, seed=7, data_cache=None)
        out, cache = prepare_run(cfg, str(tmp_path))
        assert out == tmp_path and cache == tmp_path / "data" and torch.get_num_threads() == 1
        a = torch.rand(3)
        prepare_run(cfg, tmp_path)
        assert torch.equal(a, torch.rand(3))  # the seed was set again: the same stream
        other = types.SimpleNamespace(threads=0, seed=None, data_cache=str(tmp_path / "shared"))
        assert prepare_run(other, tmp_path)[1] == tmp_path / "shared" and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(n)
