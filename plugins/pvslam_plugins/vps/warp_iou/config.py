"""Configuration of the ``warp_iou`` VPS head."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from pvslam_core.config_base import PluginConfig


class WarpIoUConfig(PluginConfig):
    match: Literal["overlap", "iou"] = Field(
        "overlap",
        description="matching score of a current thing segment g and a warped previous segment p of the same "
        "category: 'overlap' = |g & p| / |p| (PVO), 'iou' = |g & p| / |g | p|",
    )
    min_score: float = Field(
        0.1, ge=0.0, le=1.0,
        description="pairs scoring below this are not matched (the current segment gets a new id); PVO uses 0",
    )
    flow_preset: Literal["ultrafast", "fast", "medium"] = Field(
        "ultrafast",
        description="OpenCV DIS optical-flow preset used when the motion cue carries no flow (ultrafast: 0 id "
        "switches in 389 instance transitions on moving_vehicles, and the cheapest)",
    )
    flow_max_side: int = Field(
        320, ge=32,
        description="DIS flow is computed on images reduced to at most this many pixels on the longer side",
    )
    rigid_stuff: bool = Field(
        True,
        description="warp previous *stuff* pixels with depth + camera poses when the cue has depth_prev, both "
        "poses and intrinsics (things always follow the flow)",
    )
    warp_max_side: Optional[int] = Field(
        None, ge=16,
        description="warp and match the previous ids at most this many pixels on the longer side (nearest "
        "subsampling; the output ids keep the input resolution). None: full resolution. 160 at 320x240 is 4x "
        "cheaper but lost small things: VPQ-things 0.957 -> 0.896 on the driving loop with depth cues",
    )
    splat: Literal["nearest", "bilinear"] = Field(
        "bilinear",
        description="forward-warp splatting: 'nearest' writes the rounded target pixel; 'bilinear' writes all "
        "four neighbours of the target (fewer holes)",
    )
