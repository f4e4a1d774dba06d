"""Configuration of the ``synthetic`` dataset plugin."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator

from pvslam_core.datasets.base import ReaderOptions

from .render import HFOV_RANGE
from .scenario_base import MAX_FRAMES
from .scenarios import DEFAULT_SCENARIO, check_name


class SyntheticConfig(ReaderOptions):
    """Generate (and cache) a built-in synthetic sequence, or read one already written (``path``)."""

    scenario: str = Field(DEFAULT_SCENARIO, description="driving_loop | moving_vehicles | indoor_handheld | "
                          "handheld_fast | indoor_textureless | busy_street | forward_low_parallax | driving_city | "
                          "suburban_street")
    path: Optional[str] = Field(None, description="read this existing synthetic folder instead of generating")
    num_frames: Optional[int] = Field(None, ge=1, le=MAX_FRAMES,
                                      description="frames to generate; None = the scenario's default")
    laps: Optional[float] = Field(None, gt=0, description="loop scenarios: laps to drive when num_frames is None")
    width: int = Field(320, ge=16, description="image width to generate")
    height: int = Field(240, ge=16, description="image height to generate")
    seed: int = Field(0, description="scene/trajectory seed (same seed, same sequence)")
    hfov_deg: Optional[float] = Field(
        None, ge=HFOV_RANGE[0], le=HFOV_RANGE[1],
        description="another camera: its horizontal field of view in degrees (same scene and trajectory); None = the "
        "default, about 61")
    domain: Optional[Literal["train", "heldout"]] = Field(
        None, description="restyle the scene (textures, thing sizes, light, camera noise/blur, haze; from the seed): "
        "to test a segmenter on looks it never trained on ('heldout'); None = the plain scene")
    progress: bool = Field(True, description="progress bar while generating (only on a terminal)")
    gt_maps: list[Literal["depth", "panoptic", "dynamic"]] = Field(
        default_factory=lambda: ["panoptic"],
        description="ground-truth maps decoded with each frame (one PNG each): panoptic feeds the `labels` segmenter "
        "and PQ/VPQ; depth and dynamic masks only serve oracles and tests, so they are not read by default",
    )

    @field_validator("scenario")
    @classmethod
    def _known(cls, v: str) -> str:
        check_name(v)
        return v
