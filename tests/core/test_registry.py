"""Discovery through entry points, the allow-list, registration checks, unknown-plugin errors."""
from importlib import metadata

import pytest
from pydantic import BaseModel

from pvslam_core.registry import ENTRY_POINT_GROUP, PluginError, build_registry, hookimpl

BUILTIN_ENTRY_POINTS = {"synthetic", "kitti", "euroc", "tum", "vkitti2", "images", "video", "labels", "flow",
                        "classical", "dense_ba", "warp_iou"}


def test_builtins_and_example_are_discovered_through_entry_points():
    names = {ep.name for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}
    assert BUILTIN_ENTRY_POINTS <= names
    reg = build_registry()
    assert BUILTIN_ENTRY_POINTS <= set(reg.loaded_entry_points)
    assert "flow" in reg.names("frontend")
    assert {"online_ba", "offline_ba"} <= set(reg.names("optimizer"))
    assert "synthetic" in reg.names("dataset")
    # the example third-party package registers through the same group
    npz = reg.get("dataset", "npz")
    assert npz.distribution == "pvslam-npz" and npz.version == "0.1.0"
    assert reg.get("frontend", "flow").distribution == "pvslam"


def test_allow_list_restricts_loading(monkeypatch):
    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "flow, dense_ba")
    reg = build_registry()
    assert sorted(reg.loaded_entry_points) == ["dense_ba", "flow"]
    assert reg.names("dataset") == []
    assert "kitti" in reg.skipped_entry_points
    with pytest.raises(PluginError) as err:
        reg.get("dataset", "kitti")
    assert "PVSLAM_LOAD_PLUGINS" in str(err.value)


def test_empty_allow_list_loads_nothing(monkeypatch):
    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    reg = build_registry()
    assert reg.loaded_entry_points == [] and reg.plugins == {}


def test_unknown_plugin_lists_installed_and_catalogued(tmp_path, monkeypatch):
    cat = tmp_path / "registry.toml"
    cat.write_text('[[plugin]]\nname = "future_flow"\ninterface = "frontend"\nentry_point = "x.y"\n'
                   'description = "not installed"\ninstall = "pip install future-flow"\nstatus = "planned"\n')
    monkeypatch.setenv("PVSLAM_REGISTRY", str(cat))
    reg = build_registry()
    with pytest.raises(PluginError) as err:
        reg.get("frontend", "raft_flow")
    msg = str(err.value)
    assert "unknown frontend plugin 'raft_flow'" in msg
    assert "flow" in msg  # installed
    assert "future_flow" in msg and "pip install future-flow" in msg  # catalogued, not installed, with its hint


class _Loose(BaseModel):  # no extra="forbid"
    x: int = 1


class _BadPlugin:
    @staticmethod
    @hookimpl
    def register_frontends(register):
        register("loose", lambda c, ctx: None, _Loose)


def test_config_model_must_forbid_extra_keys():
    with pytest.raises(PluginError, match="extra='forbid'"):
        build_registry(extra_modules=(_BadPlugin,))


class _Dup:
    @staticmethod
    @hookimpl
    def register_frontends(register):
        from pvslam_core.config_base import PluginConfig

        register("flow", lambda c, ctx: None, PluginConfig)


def test_duplicate_names_are_rejected():
    with pytest.raises(PluginError, match="registered twice"):
        build_registry(extra_modules=(_Dup,))


def test_unknown_hook_is_caught_by_pending_check():
    class Typo:
        @staticmethod
        @hookimpl
        def register_frontend(register):  # missing "s": not a hook of pvslam
            pass

    from pluggy import PluginValidationError

    with pytest.raises(PluginValidationError):
        build_registry(extra_modules=(Typo,))


def _write_module(tmp_path, name: str, body: str) -> None:
    (tmp_path / f"{name}.py").write_text("from pvslam_core.registry import hookimpl\n" + body)


GOOD_PLUGIN = """
from pvslam_core.config_base import PluginConfig
class Cfg(PluginConfig):
    pass
@hookimpl
def register_frontends(register):
    register("good_front", lambda c, ctx: None, Cfg, description="a working third-party plugin")
"""
RAISING_HOOK = """
from pvslam_core.config_base import PluginConfig
class Cfg(PluginConfig):
    pass
@hookimpl
def register_frontends(register):
    register("half_registered", lambda c, ctx: None, Cfg)
    raise RuntimeError("needs CUDA 13 (test)")
"""


def _eps(monkeypatch, tmp_path, **modules):
    """Entry points (name -> module source) importable from ``tmp_path``, plus the real built-ins."""
    from pvslam_core import registry as r

    monkeypatch.syspath_prepend(str(tmp_path))
    eps = []
    for name, body in modules.items():
        if body is not None:
            _write_module(tmp_path, f"pvslam_test_ep_{name}", body)
        eps.append(metadata.EntryPoint(name=name, value=f"pvslam_test_ep_{name}", group=ENTRY_POINT_GROUP))
    real = r._entry_points()
    monkeypatch.setattr(r, "_entry_points", lambda: sorted(real + eps, key=lambda e: e.name))
    return r


def test_broken_entry_point_is_skipped_with_a_warning_naming_it(monkeypatch, tmp_path):
    r = _eps(monkeypatch, tmp_path, broken=None, good=GOOD_PLUGIN,
             bad_hook=RAISING_HOOK, syntax="def oops(:\n")
    with pytest.warns(r.PluginLoadWarning) as rec:
        reg = r.build_registry()
    msgs = [str(w.message) for w in rec]
    assert any("'broken'" in m and "pvslam_test_ep_broken" in m and "ModuleNotFoundError" in m for m in msgs), msgs
    assert any("'bad_hook'" in m and "needs CUDA 13" in m and "register_frontends" in m for m in msgs), msgs
    assert any("'syntax'" in m and "SyntaxError" in m for m in msgs), msgs
    assert set(reg.broken_entry_points) == {"broken", "bad_hook", "syntax"}
    assert "needs CUDA 13" in reg.broken_entry_points["bad_hook"]
    # everything else still works: the built-ins and the good third-party plugin
    assert "flow" in reg.names("frontend") and "good_front" in reg.names("frontend")
    assert "good" in reg.loaded_entry_points and "bad_hook" not in reg.loaded_entry_points
    # a hook that raised half-way leaves nothing behind
    assert "half_registered" not in reg.names("frontend")
    # asking for a broken plugin's name says why it is missing
    with pytest.raises(PluginError) as err:
        reg.get("frontend", "half_registered")
    assert "bad_hook" in str(err.value) and "needs CUDA 13" in str(err.value)


def test_allow_list_still_restricts_and_skips_broken_without_importing(monkeypatch, tmp_path):
    r = _eps(monkeypatch, tmp_path, broken=None, good=GOOD_PLUGIN)
    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "flow,good")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the broken plugin is not loaded, so nothing to warn about
        reg = r.build_registry()
    assert sorted(reg.loaded_entry_points) == ["flow", "good"] and reg.broken_entry_points == {}
    assert reg.names("frontend") == ["flow", "good_front"]


def test_allow_list_with_an_unknown_name_suggests(monkeypatch):
    from pvslam_core import registry as r

    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "flow,synthtic")
    with pytest.warns(r.PluginLoadWarning, match=r"'synthtic'.*did you mean 'synthetic'"):
        reg = r.build_registry()
    assert reg.loaded_entry_points == ["flow"]


def test_entry_point_with_invalid_registration_is_broken_not_fatal(monkeypatch, tmp_path):
    loose = """
from pydantic import BaseModel
class Loose(BaseModel):
    x: int = 1
@hookimpl
def register_frontends(register):
    register("loose", lambda c, ctx: None, Loose)
"""
    dup = """
from pvslam_core.config_base import PluginConfig
@hookimpl
def register_frontends(register):
    register("flow", lambda c, ctx: None, PluginConfig)
"""
    typo = """
@hookimpl
def register_frontend(register):
    pass
"""
    r = _eps(monkeypatch, tmp_path, loose=loose, zdup=dup, typo=typo)
    with pytest.warns(r.PluginLoadWarning):
        reg = r.build_registry()
    assert "extra='forbid'" in reg.broken_entry_points["loose"]
    assert "registered twice" in reg.broken_entry_points["zdup"]
    assert "register_frontend" in reg.broken_entry_points["typo"]
    assert reg.get("frontend", "flow").distribution == "pvslam"  # the built-in kept its name


def test_plugins_command_lists_broken_entry_points(monkeypatch, tmp_path, capsys):
    import json

    from pvslam_core.cli import main

    r = _eps(monkeypatch, tmp_path, bad_hook=RAISING_HOOK)
    with pytest.warns(r.PluginLoadWarning):
        monkeypatch.setattr(r, "_REGISTRY", r.build_registry())
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert "broken" in out and "bad_hook" in out and "needs CUDA 13" in out
    assert main(["plugins", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    (row,) = [x for x in rows if x["name"] == "bad_hook"]
    assert row["state"] == "broken" and "needs CUDA 13" in row["error"]


def test_unknown_plugin_name_gets_did_you_mean():
    reg = build_registry()
    with pytest.raises(PluginError) as err:
        reg.get("frontend", "flwo")
    msg = str(err.value)
    assert "did you mean 'flow'?" in msg and "Installed frontend plugins: flow" in msg
    with pytest.raises(PluginError) as err:
        reg.get("optimizer", "online-ba")
    assert "did you mean 'online_ba'" in str(err.value)  # the closest first


def test_registry_toml_covers_every_builtin_entry_point():
    from pvslam_core.catalog import load_catalog

    entries = load_catalog()
    assert entries, "registry.toml not found"
    reg = build_registry()
    builtins = {(e.interface, e.name) for e in entries if e.builtin}
    installed = {k for k, spec in reg.plugins.items() if spec.distribution == "pvslam"}
    assert installed == builtins
    for e in entries:
        for w in e.weights:
            assert w.url.startswith("https://") and w.license
