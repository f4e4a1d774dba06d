"""Plugin registration: pluggy hooks that receive a ``register`` callback, loaded from entry points.

A plugin package declares an entry point in the ``pvslam`` group that names a module with ``@hookimpl``
functions, for example::

    [project.entry-points.pvslam]
    my_frontend = "my_package.plugin"

    # my_package/plugin.py
    from pvslam_core.registry import hookimpl

    @hookimpl
    def register_frontends(register):
        from .config import MyConfig            # a pydantic model with extra="forbid"
        register("my_frontend", make_frontend, MyConfig, description="...")

``make_frontend(config, context)`` builds the object; it is called once per run.  Hooks only register:
the pipeline calls the selected objects directly, never a per-frame hook.  Built-in plugins go through exactly
this path (see ``pyproject.toml``).  ``PVSLAM_LOAD_PLUGINS=a,b`` restricts which entry points are loaded
(empty string: none).
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any, Callable, Optional

import pluggy

ENTRY_POINT_GROUP = "pvslam"
PROJECT = "pvslam"
INTERFACES = ("dataset", "segmenter", "frontend", "loop", "optimizer", "vps")
HOOK_FOR = {
    "dataset": "register_datasets",
    "segmenter": "register_segmenters",
    "frontend": "register_frontends",
    "loop": "register_loop_detectors",
    "optimizer": "register_optimizers",
    "vps": "register_vps_heads",
}

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


class HookSpecs:
    """One hook per interface; each receives ``register(name, factory, config_model, description="", **extras)``.

    ``extras`` are optional named capabilities the core may look up, e.g. a dataset plugin's
    ``generate(name, out_dir, **kw) -> Path`` and ``scenarios`` (used by ``pvslam synth``).
    """

    @hookspec
    def register_datasets(self, register):  # type: ignore[no-untyped-def]
        """Register :class:`~pvslam_core.interfaces.DatasetReader` factories."""

    @hookspec
    def register_segmenters(self, register):  # type: ignore[no-untyped-def]
        """Register :class:`~pvslam_core.interfaces.Segmenter` factories."""

    @hookspec
    def register_frontends(self, register):  # type: ignore[no-untyped-def]
        """Register :class:`~pvslam_core.interfaces.Frontend` factories."""

    @hookspec
    def register_loop_detectors(self, register):  # type: ignore[no-untyped-def]
        """Register :class:`~pvslam_core.interfaces.LoopDetector` factories."""

    @hookspec
    def register_optimizers(self, register):  # type: ignore[no-untyped-def]
        """Register :class:`~pvslam_core.interfaces.Optimizer` factories."""

    @hookspec
    def register_vps_heads(self, register):  # type: ignore[no-untyped-def]
        """Register :class:`~pvslam_core.interfaces.VPSHead` factories."""


class PluginError(Exception):
    """A plugin could not be found, loaded or registered."""


@dataclass
class PluginSpec:
    interface: str
    name: str
    factory: Callable[..., Any]
    config_model: type
    description: str = ""
    entry_point: str = ""  # entry-point name that registered it
    distribution: str = ""  # installed distribution that provides it
    version: str = ""
    extras: dict[str, Any] = field(default_factory=dict)  # optional capabilities, e.g. a dataset's `generate`


@dataclass
class Registry:
    plugins: dict[tuple[str, str], PluginSpec] = field(default_factory=dict)
    loaded_entry_points: list[str] = field(default_factory=list)
    skipped_entry_points: list[str] = field(default_factory=list)

    def get(self, interface: str, name: str) -> PluginSpec:
        key = (interface, name)
        if key not in self.plugins:
            raise PluginError(self._unknown_message(interface, name))
        return self.plugins[key]

    def names(self, interface: str) -> list[str]:
        return sorted(n for (i, n) in self.plugins if i == interface)

    def _unknown_message(self, interface: str, name: str) -> str:
        installed = self.names(interface)
        lines = [f"unknown {interface} plugin {name!r}."]
        lines.append("Installed " + interface + " plugins: " + (", ".join(installed) if installed else "(none)"))
        from .catalog import load_catalog  # local import: the catalog is only read on this error path

        missing = [
            e for e in load_catalog() if e.interface == interface and (interface, e.name) not in self.plugins
        ]
        if missing:
            lines.append("Known in registry.toml but not installed:")
            for e in missing:
                lines.append(f"  {e.name}: {e.description} (install: {e.install})")
        if self.skipped_entry_points:
            lines.append(
                "Entry points not loaded because of PVSLAM_LOAD_PLUGINS: " + ", ".join(self.skipped_entry_points)
            )
        return "\n".join(lines)


def _allow_list() -> Optional[set[str]]:
    raw = os.environ.get("PVSLAM_LOAD_PLUGINS")
    if raw is None:
        return None
    return {s.strip() for s in raw.split(",") if s.strip()}


def _entry_points() -> list[metadata.EntryPoint]:
    eps = metadata.entry_points()
    selected = eps.select(group=ENTRY_POINT_GROUP) if hasattr(eps, "select") else eps.get(ENTRY_POINT_GROUP, [])
    # de-duplicate (an editable install can expose one distribution twice on sys.path)
    seen: dict[str, metadata.EntryPoint] = {}
    for ep in selected:
        seen.setdefault(ep.name, ep)
    return [seen[k] for k in sorted(seen)]


def build_registry(extra_modules: tuple[Any, ...] = ()) -> Registry:
    """Load the entry points of group ``pvslam`` (filtered by ``PVSLAM_LOAD_PLUGINS``) and collect registrations.

    ``extra_modules`` are modules/objects with hookimpls registered directly (for tests and embedding).
    """
    pm = pluggy.PluginManager(PROJECT)
    pm.add_hookspecs(HookSpecs)
    reg = Registry()
    allow = _allow_list()
    origin: dict[int, tuple[str, str, str]] = {}
    for ep in _entry_points():
        if allow is not None and ep.name not in allow:
            reg.skipped_entry_points.append(ep.name)
            continue
        try:
            module = ep.load()
        except Exception as exc:  # a broken plugin must name itself, not crash with a bare traceback
            raise PluginError(
                f"entry point {ep.name!r} ({ep.value}) in group {ENTRY_POINT_GROUP!r} failed to import: "
                f"{type(exc).__name__}: {exc}"
            ) from exc
        dist = getattr(ep, "dist", None)
        dist_name = dist.metadata["Name"] if dist is not None else ""
        version = dist.version if dist is not None else ""
        if pm.is_registered(module):
            continue
        pm.register(module, name=ep.name)
        origin[id(module)] = (ep.name, dist_name, version)
        reg.loaded_entry_points.append(ep.name)
    for mod in extra_modules:
        pm.register(mod)
        origin[id(mod)] = (getattr(mod, "__name__", repr(mod)), "", "")
    pm.check_pending()

    for interface, hook_name in HOOK_FOR.items():
        hook = getattr(pm.hook, hook_name)
        for impl in hook.get_hookimpls():
            ep_name, dist_name, version = origin.get(id(impl.plugin), (impl.plugin_name, "", ""))

            def register(name: str, factory: Callable[..., Any], config_model: type, description: str = "",
                         _i: str = interface, _ep: str = ep_name, _d: str = dist_name, _v: str = version,
                         **extras: Any) -> None:
                _check_config_model(_i, name, config_model)
                key = (_i, name)
                if key in reg.plugins:
                    prev = reg.plugins[key]
                    raise PluginError(
                        f"{_i} plugin {name!r} is registered twice: by entry point {prev.entry_point!r} "
                        f"and by {_ep!r}"
                    )
                reg.plugins[key] = PluginSpec(_i, name, factory, config_model, description, _ep, _d, _v, extras)

            impl.function(register=register)
    return reg


def _check_config_model(interface: str, name: str, model: type) -> None:
    from pydantic import BaseModel

    if not (isinstance(model, type) and issubclass(model, BaseModel)):
        raise PluginError(f"{interface} plugin {name!r}: config_model must be a pydantic BaseModel subclass")
    if model.model_config.get("extra") != "forbid":
        raise PluginError(
            f"{interface} plugin {name!r}: config model {model.__name__} must set extra='forbid' "
            "so that typos in configs are caught"
        )


_REGISTRY: Optional[Registry] = None


def get_registry(refresh: bool = False) -> Registry:
    """The process-wide registry (built lazily on first use)."""
    global _REGISTRY
    if _REGISTRY is None or refresh:
        _REGISTRY = build_registry()
    return _REGISTRY


def python_version() -> str:
    return sys.version.split()[0]
