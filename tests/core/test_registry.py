"""Discovery through entry points, the allow-list, registration checks, unknown-plugin errors."""
from importlib import metadata

import pytest
from pydantic import BaseModel

from pvslam_core.registry import ENTRY_POINT_GROUP, PluginError, build_registry, hookimpl

BUILTIN_ENTRY_POINTS = {"synthetic", "kitti", "euroc", "tum", "vkitti2", "images", "video", "labels", "flow",
                        "classical_loop", "online_ba", "offline_ba", "warp_iou"}


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
    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "flow, online_ba")
    reg = build_registry()
    assert sorted(reg.loaded_entry_points) == ["flow", "online_ba"]
    assert reg.names("dataset") == []
    assert "kitti" in reg.skipped_entry_points
    with pytest.raises(PluginError) as err:
        reg.get("dataset", "kitti")
    assert "PVSLAM_LOAD_PLUGINS" in str(err.value)


def test_empty_allow_list_loads_nothing(monkeypatch):
    monkeypatch.setenv("PVSLAM_LOAD_PLUGINS", "")
    reg = build_registry()
    assert reg.loaded_entry_points == [] and reg.plugins == {}


def test_unknown_plugin_lists_installed_and_catalogued():
    reg = build_registry()
    with pytest.raises(PluginError) as err:
        reg.get("frontend", "raft_flow")
    msg = str(err.value)
    assert "unknown frontend plugin 'raft_flow'" in msg
    assert "flow" in msg  # installed
    assert "droid" in msg and "install:" in msg  # registry.toml entry that is not installed, with its hint


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


def test_broken_entry_point_names_itself(monkeypatch):
    from pvslam_core import registry as r

    bad = metadata.EntryPoint(name="broken", value="pvslam_no_such_module_xyz", group=ENTRY_POINT_GROUP)
    monkeypatch.setattr(r, "_entry_points", lambda: [bad])
    with pytest.raises(PluginError, match="'broken'.*failed to import"):
        r.build_registry()


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
