"""Configuration of the dense BA optimizer: one model, and the two registered schedules as default presets.

The BA's fixed constants (damping of each call kind, the pose graph's settings and checks) live next to the code
that uses them in :mod:`.optimizer`; ``retired`` lists the keys that set them in earlier releases."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from pvslam_core.config_base import PluginConfig


class LoopBAConfig(PluginConfig):
    """The loop closure's BA: a Sim(3) pose graph of the drift, then a relaxed BA over the loop."""

    iters: int = Field(4, ge=0, description="Gauss-Newton iterations of the relaxed loop BA after the pose graph "
                       "(docs/decisions.md: optimizer.loop.iters)")
    sim3_pgo: bool = Field(True, description="run a Sim(3) pose-graph correction of the drift before the loop BA "
                           "(skipped where a depth or distance prior observes the scale; docs/decisions.md: "
                           "optimizer.loop.sim3_pgo)")


class FinalBAConfig(PluginConfig):
    """The global BA over every keyframe in finalize()."""

    iters: int = Field(4, ge=0, description="Gauss-Newton iterations per round of the global BA (0: none)")
    rounds: int = Field(1, ge=0, description="observe -> global BA rounds (re-observing lets a learned frontend "
                        "refine its targets)")


class OfflineFinalBAConfig(FinalBAConfig):
    """``offline_ba``'s global BA: DROID's backend runs more update / BA rounds than the online schedule needs."""

    iters: int = Field(8, ge=0, description="Gauss-Newton iterations per round of the global BA (0: none)")
    rounds: int = Field(2, ge=0, description="observe -> global BA rounds (re-observing lets a learned frontend "
                        "refine its targets)")


class BAConfigBase(PluginConfig):
    """Parameters of the dense BA optimizer (the defaults are DROID-SLAM's frontend / backend constants)."""

    # pgo_min_gap: the loop policy's loop_closure.ba_min_gap gates loop BAs (and with them the pose graph)
    renamed = {"loop_iters": "loop.iters", "sim3_pgo": "loop.sim3_pgo", "final_iters": "final.iters",
               "final_rounds": "final.rounds", "pgo_min_gap": None}
    # now constants of optimizer.py (eta: the name of depth_damping before it)
    retired = {"eta": 1e-5, "depth_damping": 1e-5, "lm": 1e-4, "ep": 0.1, "min_depth": 0.2, "loop_window": 0,
               "loop_lm": 1e-5, "loop_ep": 1e-2, "final_lm": 1e-5, "final_ep": 1e-2, "pgo_iters": 25,
               "pgo_min_drift": 0.02, "pgo_loop_weight": 10.0, "pgo_max_direction_deg": 15.0,
               "pgo_max_scale_disagreement": 1.25, "pgo_min_pixels": 30,
               # opt-in paths that no shipped configuration enabled, deleted with their code
               "iters_max": None, "iters_tol": 0.01, "depth_damping_shrink": False, "depth_damping_horizon": 50,
               "sim3_pgo_with_depth_prior": False}

    window: int = Field(12, ge=1, description="sliding window: the last `window` keyframes have free poses")
    iters: int = Field(2, ge=0, description="Gauss-Newton iterations per step() call")
    robust: Optional[Literal["none", "huber", "cauchy"]] = Field(
        "cauchy", description="robust (IRLS) kernel on the 2D residual ('none', 'huber', 'cauchy'): classical flow has "
        "gross outliers (road, occlusions) its confidences miss (docs/decisions.md: optimizer.robust)")
    robust_scale: float = Field(1.0, gt=0, description="robust kernel scale in BA-resolution pixels")
    loop: LoopBAConfig = Field(default_factory=LoopBAConfig, description="the loop closure's pose graph and BA")
    final: FinalBAConfig = Field(default_factory=FinalBAConfig, description="the global BA at the end")


class OnlineBAConfig(BAConfigBase):
    """``online_ba``: PV-SLAM's online BA (a sliding-window BA as each keyframe arrives)."""

    window: int = Field(10, ge=1, description="sliding window: the last `window` keyframes have free poses")
    iters: int = Field(3, ge=0, description="Gauss-Newton iterations per step() call (per keyframe update): a "
                       "classical frontend observes once per keyframe (docs/decisions.md: optimizer.iters)")


class OfflineBAConfig(BAConfigBase):
    """``offline_ba``: DROID-SLAM's schedule (small local BA per keyframe, global BA at the end)."""

    window: int = Field(7, ge=1, description="local window: the last `window` keyframes have free poses")
    final: OfflineFinalBAConfig = Field(default_factory=OfflineFinalBAConfig, description="the global BA at the end")
