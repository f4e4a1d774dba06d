"""Base class for every configuration model in pvslam (core and plugins)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class PluginConfig(BaseModel):
    """Plugin parameters: unknown keys are errors (``extra="forbid"``), so typos never pass silently."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)
