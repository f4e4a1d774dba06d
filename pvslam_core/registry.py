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

One broken third-party plugin must not take every command down: an entry point that fails to import, whose hook
raises, or that registers something invalid (a config model without ``extra="forbid"``, a name another plugin
already has, a hook name with a typo) is skipped as a whole -- none of its registrations are kept -- with a
:class:`PluginLoadWarning` naming the entry point and the error; ``pvslam plugins`` lists it as broken.  Modules
passed directly to :func:`build_registry` (tests, embedding) still raise: their caller asked for them.
"""
from __future__ import annotations

import difflib
import os
import sys
import warnings
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
    ``generate(name, out_dir, **kw) -> Path`` and ``scenarios`` (used by ``pvslam synth``), a segmenter's
    ``needs_gt_panoptic`` / ``auto_ready`` and a frontend's fixed ``ba_downsample`` (:mod:`pvslam_core.adapt`).
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


class PluginLoadWarning(UserWarning):
    """A plugin entry point was skipped: it failed to import or to register (the message says which and why)."""


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
    skipped_entry_points: list[str] = field(default_factory=list)  # not in PVSLAM_LOAD_PLUGINS
    broken_entry_points: dict[str, str] = field(default_factory=dict)  # entry point -> why it was skipped

    def get(self, interface: str, name: str) -> PluginSpec:
        key = (interface, name)
        if key not in self.plugins:
            raise PluginError(self._unknown_message(interface, name))
        return self.plugins[key]

    def names(self, interface: str) -> list[str]:
        return sorted(n for (i, n) in self.plugins if i == interface)

    def _unknown_message(self, interface: str, name: str) -> str:
        from .catalog import load_catalog  # local import: the catalog is only read on this error path

        installed = self.names(interface)
        missing = [
            e for e in load_catalog() if e.interface == interface and (interface, e.name) not in self.plugins
        ]
        close = difflib.get_close_matches(name, installed + [e.name for e in missing], n=3, cutoff=0.6)
        hint = ("; did you mean " + " or ".join(repr(c) for c in close) + "?") if close else "."
        lines = [f"unknown {interface} plugin {name!r}{hint}"]
        lines.append("Installed " + interface + " plugins: " + (", ".join(installed) if installed else "(none)"))
        if missing:
            lines.append("Known in registry.toml but not installed:")
            for e in missing:
                lines.append(f"  {e.name}: {e.description} (install: {e.install})")
        if self.skipped_entry_points:
            lines.append(
                "Entry points not loaded because of PVSLAM_LOAD_PLUGINS: " + ", ".join(self.skipped_entry_points)
            )
        for ep, why in self.broken_entry_points.items():
            lines.append(f"Entry point {ep!r} is broken and was skipped: {why}")
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


def _warn_broken(reg: Registry, name: str, value: str, why: str) -> None:
    reg.broken_entry_points[name] = why
    warnings.warn(f"pvslam: skipping plugin entry point {name!r} ({value}): {why}", PluginLoadWarning, stacklevel=3)


def build_registry(extra_modules: tuple[Any, ...] = ()) -> Registry:
    """Load the entry points of group ``pvslam`` (filtered by ``PVSLAM_LOAD_PLUGINS``) and collect registrations.

    ``extra_modules`` are modules/objects with hookimpls registered directly (for tests and embedding); an error
    in one of them raises, while a broken entry point is skipped with a :class:`PluginLoadWarning`.
    """
    pm = pluggy.PluginManager(PROJECT)
    pm.add_hookspecs(HookSpecs)
    reg = Registry()
    sources = _load_entry_points(pm, reg)
    for mod in extra_modules:
        pm.register(mod)
        sources.append((mod, None, getattr(mod, "__name__", repr(mod)), "", ""))
    pm.check_pending()

    # Each plugin's hooks run as one transaction: a hook that raises, or an invalid registration, discards
    # everything that plugin registered, so a half-registered plugin never appears.
    impls: dict[int, list[tuple[str, Any]]] = {}
    for interface, hook_name in HOOK_FOR.items():
        for impl in getattr(pm.hook, hook_name).get_hookimpls():
            impls.setdefault(id(impl.plugin), []).append((interface, impl))
    for plugin, ep_name, value, dist_name, version in sources:
        try:
            staged = _registrations(reg, impls.get(id(plugin), []), ep_name or value, dist_name, version)
        except PluginError as exc:
            if ep_name is None:  # a module the caller passed in: its errors are the caller's to see
                raise
            pm.unregister(plugin)
            _warn_broken(reg, ep_name, value, str(exc))
            continue
        reg.plugins.update(staged)
        if ep_name is not None:
            reg.loaded_entry_points.append(ep_name)
    return reg


# (plugin object, entry-point name or None for extra modules, entry-point value, distribution, version)
_Source = tuple[Any, Optional[str], str, str, str]


def _load_entry_points(pm: pluggy.PluginManager, reg: Registry) -> list[_Source]:
    """Import and register the allowed entry points' modules; a broken one is skipped with a warning."""
    allow = _allow_list()
    eps = _entry_points()
    sources: list[_Source] = []
    for ep in eps:
        if allow is not None and ep.name not in allow:
            reg.skipped_entry_points.append(ep.name)
            continue
        try:
            module = ep.load()
        except Exception as exc:  # noqa: BLE001 - any import failure: skip this plugin, name it and why
            _warn_broken(reg, ep.name, ep.value, f"failed to import: {type(exc).__name__}: {exc}")
            continue
        if pm.is_registered(module):
            continue
        try:
            pm.register(module, name=ep.name)
            pm.check_pending()  # a hook name with a typo is this entry point's fault
        except Exception as exc:  # noqa: BLE001
            if pm.is_registered(module):
                pm.unregister(module)
            _warn_broken(reg, ep.name, ep.value, f"invalid hooks: {type(exc).__name__}: {exc}")
            continue
        dist = getattr(ep, "dist", None)
        sources.append((module, ep.name, ep.value, dist.metadata["Name"] if dist is not None else "",
                        dist.version if dist is not None else ""))
    if allow:
        known = [ep.name for ep in eps]
        for name in sorted(allow - set(known)):
            close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
            warnings.warn(f"PVSLAM_LOAD_PLUGINS names {name!r}, which is no installed entry point"
                          + (f"; did you mean {close[0]!r}?" if close else "")
                          + " Installed: " + ", ".join(known), PluginLoadWarning, stacklevel=3)
    return sources


def _registrations(reg: Registry, impls: list[tuple[str, Any]], label: str, dist_name: str,
                   version: str) -> dict[tuple[str, str], PluginSpec]:
    """Run one plugin's hooks; returns what they registered (raises :class:`PluginError`: nothing is kept)."""
    staged: dict[tuple[str, str], PluginSpec] = {}
    for interface, impl in impls:
        def register(name: str, factory: Callable[..., Any], config_model: type, description: str = "",
                     _i: str = interface, **extras: Any) -> None:
            _check_config_model(_i, name, config_model)
            key = (_i, name)
            prev = reg.plugins.get(key) or staged.get(key)
            if prev is not None:
                raise PluginError(f"{_i} plugin {name!r} is registered twice: by entry point "
                                  f"{prev.entry_point!r} and by {label!r}")
            staged[key] = PluginSpec(_i, name, factory, config_model, description, label, dist_name, version,
                                     extras)

        try:
            impl.function(register=register)
        except PluginError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise PluginError(f"its {HOOK_FOR[interface]} hook raised {type(exc).__name__}: {exc}") from exc
    return staged


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
