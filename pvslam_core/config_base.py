"""Base class for every configuration model in pvslam (core and plugins)."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, model_validator

LOG = logging.getLogger("pvslam.config")


@dataclass(frozen=True)
class Retired:
    """A retired key's fixed ``value`` now, and the defaults it had in ``earlier`` releases (their files store them)."""

    value: Any
    earlier: tuple = ()


def retired_value(fixed: Any) -> Any:
    """The value a ``retired`` entry fixes now (a plain value, or a :class:`Retired`'s ``value``)."""
    return fixed.value if isinstance(fixed, Retired) else fixed


class PluginConfig(BaseModel):
    """Plugin parameters: unknown keys are errors (``extra="forbid"``), so typos never pass silently.

    Keys of earlier releases, so that old config files and the ``config.json`` of old run directories still load:

    * ``renamed = {"old": "new"}``: the key moved; ``"new"`` may be a dotted path into a nested table
      (``{"warmup": "init.warmup"}``), or ``None`` when the key was removed and is ignored.  A file that still uses
      the old name loads, with one warning per table that names the new keys; both names with different values
      are an error.
    * ``retired = {"old": value}``: the setting became a fixed part of the method (a constant in the code).  A file
      that gives exactly ``value`` loads (old run directories store every key); any other value is an error that
      says so, since the run would not do what the file asks.  When the constant changes later, ``Retired(value,
      earlier=(old default, ...))``: a file of an earlier release stores that release's default, which loads with a
      warning that the method now uses ``value``.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)
    renamed: ClassVar[dict[str, Any]] = {}
    retired: ClassVar[dict[str, Any]] = {}

    @model_validator(mode="before")
    @classmethod
    def _old_keys(cls, data: Any) -> Any:
        if not (cls.renamed or cls.retired) or not isinstance(data, dict):
            return data
        out = dict(data)
        moved, ignored = [], []
        for old, new in cls.renamed.items():
            if old not in out:
                continue
            value = out.pop(old)
            if new is None:
                ignored.append(old)
                continue
            *tables, key = new.split(".")
            node = out
            for t in tables:  # nested tables are copied, never changed in place
                node[t] = dict(node.get(t) or {})
                node = node[t]
            if key in node:
                if node[key] != value:  # e.g. --set with the old name over a file with the new one: neither may win
                    raise ValueError(f"keys {old!r} (its old name) and {new!r} are both given, with different values "
                                     f"({value!r}, {node[key]!r}); give {new!r} only")
            else:
                node[key] = value
                moved.append(f"{old} -> {new}")
        if moved:
            LOG.warning("%s: config keys of an earlier release, now named: %s", cls.__name__, ", ".join(moved))
        if ignored:
            LOG.warning("%s: config keys no longer used, ignored: %s", cls.__name__, ", ".join(ignored))
        stale = []
        for old, fixed in cls.retired.items():
            if old not in out:
                continue
            value = out.pop(old)
            now, earlier = retired_value(fixed), fixed.earlier if isinstance(fixed, Retired) else ()
            if value == now:
                continue
            if value in earlier:
                stale.append(f"{old} = {value!r} (now {now!r})")
                continue
            raise ValueError(f"key {old!r} was retired: its setting is now fixed at {now!r} (got {value!r}); "
                             "remove the key (docs/decisions.md says why)")
        if stale:
            LOG.warning("%s: config keys of an earlier release at that release's defaults, which the method has since "
                        "changed (docs/decisions.md says why): %s", cls.__name__, ", ".join(stale))
        return out
