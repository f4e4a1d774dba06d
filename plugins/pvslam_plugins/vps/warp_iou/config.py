"""Configuration of the ``warp_iou`` VPS head."""
from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field

from pvslam_core.config_base import PluginConfig


class WarpIoUConfig(PluginConfig):
    match: Literal["overlap", "iou"] = Field(
        "overlap", description="matching score of a current thing segment g and a warped previous one p of the same "
        "category: 'overlap' = |g & p| / |p| (PVO), 'iou' = |g & p| / |g | p|")
    min_score: float = Field(
        0.1, ge=0.0, le=1.0,
        description="pairs scoring below this are not matched (the current segment gets a new id); PVO uses 0")
    # the warping settings are constants of ..matching (WarpOptions); warp_max_side (matching at a reduced
    # resolution) was removed: it lost small things (docs/decisions.md: vps.warp_max_side)
    retired: ClassVar[dict[str, Any]] = {"flow_preset": "ultrafast", "flow_max_side": 320, "rigid_stuff": True,
                                         "splat": "bilinear", "warp_max_side": None}
