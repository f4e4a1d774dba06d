"""Configuration of the ``fusion`` VPS head."""
from __future__ import annotations

from typing import Any, ClassVar, Literal, Optional

from pydantic import Field

from pvslam_core.config_base import PluginConfig
from pvslam_plugins.segmenters.panoptic_fpn.config import PresetName


class FusionConfig(PluginConfig):
    preset: PresetName = Field(
        "reduced", description="PanopticFPN architecture whose heads decode the fused features; must be the "
        "segmenter's (the head reads the segmenter's FPN features from each segmentation)")
    segmenter_weights: Optional[str] = Field(
        None, description="the segmenter's weights (catalogue name or path); default: the preset's, as in "
        "segmenter panoptic_fpn (the shipped reduced checkpoint)")
    weights: Optional[str] = Field(
        None, description="fusion layer weights (`fusion_conv1.weight/bias`: ours or PVO's panFPN.pth) or a catalogue "
        "name; default: the shipped ones for the reduced preset, else identity (fused = current)")
    proposals: Optional[int] = Field(None, ge=1, description="RPN proposals kept for the fused decode (default: "
                                     "the preset's, 100 for reduced); fewer is cheaper")
    fuse: bool = Field(True, description="False: decode nothing, only track the segmenter's ids (like warp_iou, "
                       "plus the track memory)")
    z_order: bool = Field(True, description="forward-warp features with depth z-ordering when the motion cue has "
                          "depth (near surfaces win); PVO's default is last write wins")
    rigid_static: bool = Field(True, description="warp the previous frame's stuff with the rigid flow of depth + "
                               "camera poses when the cue has them (things always follow the VO flow)")
    match: Literal["overlap", "iou"] = Field("overlap", description="matching score (see warp_iou): 'overlap' = "
                                             "|g & p| / |p| (PVO)")
    min_score: float = Field(0.1, ge=0.0, le=1.0, description="pairs scoring below this are not matched")
    memory_frames: int = Field(10, ge=0, description="remember a lost thing track this many frames (0 = off): a "
                               "segment reappearing where the track is predicted gets its id back")
    memory_min_score: float = Field(0.5, gt=0.0, le=1.0, description="fraction of a reappearing segment that must "
                                    "lie inside the lost track's predicted mask")
    threads: int = Field(0, ge=0, description="torch threads for the fusion and decode (0 = leave as is)")
    # the DIS flow and splatting settings are the warp_iou head's (constants of ..matching)
    retired: ClassVar[dict[str, Any]] = {"flow_preset": "ultrafast", "flow_max_side": 320, "splat": "bilinear"}
