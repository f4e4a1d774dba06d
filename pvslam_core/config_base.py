"""Base class for every configuration model in pvslam (core and plugins)."""
from __future__ import annotations

import logging
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, model_validator

LOG = logging.getLogger("pvslam.config")


class PluginConfig(BaseModel):
    """Plugin parameters: unknown keys are errors (``extra="forbid"``), so typos never pass silently.

    Renamed keys: a subclass lists ``renamed = {"old": "new"}`` (``"new"`` = ``None``: the key was removed and is
    ignored); files that still use an old name keep working for one release, with a warning that names the new key.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)
    renamed: ClassVar[dict[str, Any]] = {}

    @model_validator(mode="before")
    @classmethod
    def _renamed_keys(cls, data: Any) -> Any:
        if not cls.renamed or not isinstance(data, dict):
            return data
        out = dict(data)
        for old, new in cls.renamed.items():
            if old not in out:
                continue
            value = out.pop(old)
            if new is None:
                LOG.warning("config key %r of %s is no longer used and is ignored", old, cls.__name__)
            elif new in out:
                LOG.warning("config keys %r (deprecated) and %r both given in %s; using %r", old, new,
                            cls.__name__, new)
            else:
                LOG.warning("config key %r of %s is deprecated; use %r", old, cls.__name__, new)
                out[new] = value
        return out
