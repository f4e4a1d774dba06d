"""Config validation errors, --set overrides, resolved-config round trip, ablation files."""
import json

import pytest

from pvslam_core.config import (ConfigError, apply_overrides, load_ablation, load_config, parse_override,
                                parse_value)


def test_defaults_resolve_with_builtin_plugins():
    cfg = load_config()
    assert cfg.pipeline.dataset.plugin == "synthetic"
    assert cfg.pipeline.frontend.plugin == "flow"
    # every plugin parameter is filled in from the plugin's own model
    assert cfg.pipeline.frontend.params == cfg.models["frontend"].model_dump(mode="json")
    assert cfg.pipeline.frontend.params  # non-empty


def test_typo_in_core_section_names_file_key_and_allowed(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[graph]\nwarmupp = 3\n")
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert str(p) in msg and "graph.warmupp" in msg
    assert "allowed keys here:" in msg and "init" in msg and "edges" in msg and "ba_downsample" in msg


def test_typo_in_plugin_params_lists_the_plugins_keys(tmp_path, fake_registry):
    p = tmp_path / "bad.toml"
    p.write_text('[frontend]\nplugin = "exact"\nkeyframe_evry = 3\n')
    with pytest.raises(ConfigError) as err:
        load_config(p, registry=fake_registry)
    msg = str(err.value)
    assert str(p) in msg and "frontend.keyframe_evry" in msg and "keyframe_every" in msg


def test_wrong_type_and_literal_values(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('[evaluation]\nalign = "affine"\n')
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert "evaluation.align" in msg and "'sim3'" in msg and "'se3'" in msg and "affine" in msg


def test_unknown_plugin_in_config(tmp_path, monkeypatch):
    """A catalogued but uninstalled plugin: the error lists what is installed and how to install it."""
    reg = tmp_path / "registry.toml"
    reg.write_text('[[plugin]]\nname = "future_loop"\ninterface = "loop"\nentry_point = "x.y"\n'
                   'description = "not installed"\ninstall = "pip install future-loop"\nstatus = "planned"\n')
    monkeypatch.setenv("PVSLAM_REGISTRY", str(reg))
    p = tmp_path / "bad.toml"
    p.write_text('[loop]\nplugin = "future_loop"\n')
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert "loop.plugin" in msg and "classical" in msg and "future_loop" in msg and "pip install future-loop" in msg


def test_required_component_cannot_be_none():
    with pytest.raises(ConfigError, match="frontend.plugin cannot be 'none'"):
        load_config(overrides=["frontend.plugin=none"])


def test_disabled_component_with_params_is_an_error():
    with pytest.raises(ConfigError, match="switched off"):
        load_config(overrides={"loop.plugin": "none", "loop.threshold": 0.5})


def test_invalid_toml_names_the_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[run\nname=")
    with pytest.raises(ConfigError, match="broken.toml: not valid TOML"):
        load_config(p)


def test_set_overrides_parse_toml_values():
    assert parse_override("graph.init.warmup=7") == ("graph.init.warmup", 7)
    assert parse_override("run.progress=false") == ("run.progress", False)
    assert parse_override("evaluation.vpq_ks=[0, 5]") == ("evaluation.vpq_ks", [0, 5])
    assert parse_override("dataset.path=/data/kitti") == ("dataset.path", "/data/kitti")
    assert parse_value('"quoted"') == "quoted"
    with pytest.raises(ConfigError):
        parse_override("graph.warmup")
    cfg = load_config(overrides=["graph.init.warmup=7", "loop.plugin=none", "run.name=abc"])
    assert cfg.pipeline.graph.init.warmup == 7 and not cfg.pipeline.loop.enabled and cfg.pipeline.run.name == "abc"
    assert cfg.models["loop"] is None


def test_null_unsets_an_optional_key(tmp_path):
    """An optional key set in a config file can be set back to None from the command line; ``none`` stays the
    plugin name, and null on a required key is an error naming it."""
    cfg_file = tmp_path / "c.toml"
    cfg_file.write_text("[run]\nmax_frames = 3\n")
    assert load_config(cfg_file).pipeline.run.max_frames == 3
    assert load_config(cfg_file, overrides=["run.max_frames=null"]).pipeline.run.max_frames is None
    assert parse_value("none") == "none" and parse_value("null") is None
    with pytest.raises(ConfigError) as err:
        load_config(overrides=["graph.init.warmup=null"])
    assert "graph.init.warmup" in str(err.value)


def test_override_typo_is_reported():
    with pytest.raises(ConfigError) as err:
        load_config(overrides=["graph.warmpu=7"])
    assert "graph.warmpu" in str(err.value) and "--set" in str(err.value)


def test_apply_overrides_does_not_mutate_and_expands_shorthand():
    raw = {"dataset": "kitti"}
    out = apply_overrides(raw, {"dataset.sequence": "06"})
    assert raw == {"dataset": "kitti"}
    assert out == {"dataset": {"plugin": "kitti", "sequence": "06"}}


def test_resolved_config_reloads_identically(tmp_path, fake_registry, fake_config_file):
    cfg = load_config(fake_config_file, overrides=["graph.init.warmup=4"], registry=fake_registry)
    path = tmp_path / "config.json"
    path.write_text(cfg.to_json())
    again = load_config(path, registry=fake_registry)
    assert again.pipeline == cfg.pipeline
    assert again.models == cfg.models
    assert json.loads(again.to_json()) == json.loads(cfg.to_json())
    # the builtin default too
    d = load_config()
    p2 = tmp_path / "d.json"
    p2.write_text(d.to_json())
    assert load_config(p2).pipeline == d.pipeline


ABLATION = """
[run]
progress = false
[loop]
plugin = "classical"

[[variant]]
name = "full"

[[variant]]
name = "no_loop"
"loop.plugin" = "none"

[[variant]]
name = "offline"
"optimizer.plugin" = "offline_ba"
"graph.init.warmup" = 6
"""


def test_ablation_variants(tmp_path):
    p = tmp_path / "abl.toml"
    p.write_text(ABLATION)
    variants = load_ablation(p, overrides=["run.name=x"])
    assert [v.name for v in variants] == ["full", "no_loop", "offline"]
    assert variants[0].config.pipeline.loop.plugin == "classical"
    assert not variants[1].config.pipeline.loop.enabled
    assert variants[2].config.pipeline.optimizer.plugin == "offline_ba"
    assert variants[2].config.pipeline.graph.init.warmup == 6
    assert all(v.config.pipeline.run.name == "x" for v in variants)
    with pytest.raises(ConfigError, match="ablation file"):
        load_config(p)


def test_ablation_errors_name_the_variant(tmp_path):
    p = tmp_path / "abl.toml"
    p.write_text(ABLATION + '\n[[variant]]\nname = "bad"\n"graph.wrmup" = 3\n')
    with pytest.raises(ConfigError) as err:
        load_ablation(p)
    assert "variant 'bad'" in str(err.value) and "graph.wrmup" in str(err.value)
    p.write_text('[[variant]]\nname = "t"\n[variant.loop]\nplugin = "none"\n')
    with pytest.raises(ConfigError, match="one-level dotted keys"):
        load_ablation(p)


def test_dict_and_model_configs_resolve_like_toml(tmp_path):
    """The imported API takes a TOML-shaped dict or a PipelineConfig too; typos still fail with the key path."""
    from pvslam_core.config import PipelineConfig

    p = tmp_path / "c.toml"
    p.write_text('[graph.init]\nwarmup = 7\n[loop]\nplugin = "none"\n')
    from_file = load_config(p)
    from_dict = load_config({"graph": {"init": {"warmup": 7}}, "loop": {"plugin": "none"}})
    from_model = load_config(from_dict.pipeline)
    assert from_dict.pipeline == from_file.pipeline == from_model.pipeline
    with pytest.raises(ConfigError, match="graph.warmupp"):
        load_config({"graph": {"warmupp": 7}})
    assert load_config({"loop": {"plugin": "none"}}, overrides=["graph.init.warmup=9"]).pipeline.graph.init.warmup == 9
    assert isinstance(from_model.pipeline, PipelineConfig)
