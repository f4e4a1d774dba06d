"""Configuration of the dense BA optimizer: one model, and the two registered schedules as default presets."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field

from pvslam_core.config_base import PluginConfig


class BAConfigBase(PluginConfig):
    """Parameters of the dense BA optimizer (the defaults are DROID-SLAM's frontend / backend constants)."""

    # pgo_min_gap: the loop policy's loop_closure.ba_min_gap gates loop BAs (and with them the pose graph)
    renamed = {"eta": "depth_damping", "pgo_min_gap": None}

    window: int = Field(12, ge=1, description="sliding window: the last `window` keyframes have free poses")
    iters: int = Field(2, ge=0, description="Gauss-Newton iterations per step() call")
    iters_max: Optional[int] = Field(
        None, ge=0, description="adaptive window BA: after `iters` iterations go on, up to this many, while the last "
        "iteration lowered the robust (IRLS) objective by more than iters_tol of it (None or <= iters: always `iters`); "
        "the loop and final BAs keep their fixed counts")
    iters_tol: float = Field(0.01, ge=0, description="relative decrease of the robust objective in the last iteration "
                             "below which the adaptive window BA stops (with iters_max)")
    lm: float = Field(1e-4, ge=0, description="multiplicative LM damping of the reduced pose system (S_kk += lm S_kk)")
    ep: float = Field(0.1, ge=0, description="additive LM damping of the reduced pose system (S_kk += ep)")
    depth_damping: float = Field(1e-5, ge=0, description="inverse-depth damping added to C (DROID's eta; used when "
                                 "the frontend gives no learned damping); "
                       "with exact flow on 150 driving-loop frames 1e-3 left 0.88 % ATE (depths never converge in "
                       "the window), 1e-5 gave 0.007 %")
    depth_damping_shrink: bool = Field(
        False, description="Divide depth_damping by max(1, m)^2, m the median inverse depth of the last "
        "depth_damping_horizon keyframes: depth_damping holds at the initialiser's gauge (median inverse depth 1) "
        "and keeps its weight against the data when the map shrinks (C falls with the squared baseline; with a "
        "fixed eta a shrinking map can stop converging and keep shrinking). Helps driving scenes, costs the "
        "fast hand-held ones; off by default (bench/RESULTS.md, issue 13, session 2026-12-02 i). False: the "
        "absolute eta of DROID-SLAM")
    depth_damping_horizon: int = Field(
        50, ge=1, description="keyframes whose median inverse depth measures the map's scale for "
        "depth_damping_shrink (~5 BA windows: a passing near object does not move it)")
    min_depth: float = Field(0.2, gt=0, description="points with relative depth z_j/z_i below this get zero weight")
    robust: Optional[Literal["none", "huber", "cauchy"]] = Field(
        "cauchy", description="robust (IRLS) kernel on the 2D residual: 'none', 'huber' or 'cauchy'. Classical flow has "
        "gross outliers (road, occlusions) that the confidences miss; on the 488-frame driving loop (online BA + "
        "loop closure, one observe round per keyframe) least squares gave 11.5 % ATE, Huber(1 px) 5.7 %, "
        "Cauchy(1 px) 0.17-0.19 %")
    robust_scale: float = Field(1.0, gt=0, description="robust kernel scale in BA-resolution pixels")
    loop_window: int = Field(0, ge=0, description="loop BA frees keyframes newer than n - loop_window (0: from the "
                             "oldest loop keyframe on, i.e. the window spans the loop)")
    loop_iters: int = Field(
        4, ge=0, description="Gauss-Newton iterations of the relaxed loop BA (after the Sim(3) pose graph has moved "
        "the chain, 4 give the same ATE as 8 on the driving loop and its 3000-frame version at half the cost; "
        "bench/RESULTS.md, issue 14)")
    loop_lm: float = Field(1e-5, ge=0, description="multiplicative damping of the loop BA")
    loop_ep: float = Field(1e-2, ge=0, description="additive damping of the loop BA")
    sim3_pgo: bool = Field(True, description="run a Sim(3) pose-graph correction before the loop BA")
    sim3_pgo_with_depth_prior: bool = Field(
        False, description="run the Sim(3) pose graph also for a loop whose observations carry an inverse-depth "
        "prior (EdgeObservations.disp_prior, e.g. the flow frontend's road depth prior) or a distance prior "
        "(EdgeObservations.dist_prior, the road's distance between keyframes): the prior observes the "
        "scale, so a scale correction only fights it (ORB-SLAM closes stereo / RGB-D loops in SE(3)); without the "
        "pose graph the loop BA alone corrects the loop")
    pgo_iters: int = Field(25, ge=1, description="Levenberg-Marquardt iterations of the Sim(3) pose graph")
    pgo_min_drift: float = Field(0.02, ge=0, description="run the Sim(3) pose graph only when a loop measurement "
                                 "disagrees with the current estimate by more than this in |log scale|, rotation "
                                 "(rad) or translation / median depth of the old keyframe; smaller drift is left to "
                                 "the loop BA (on repeated laps the drift is corrected at the first revisit)")
    pgo_loop_weight: float = Field(10.0, gt=0, description="information weight of loop edges relative to "
                                   "odometry edges in the pose graph")
    pgo_max_direction_deg: Optional[float] = Field(
        15.0, gt=0, le=90,
        description="leave a loop edge out of the pose graph when its measurement (motion-only BA of the new "
        "keyframe against the old one's depth) puts the translation more than this many degrees off the direction "
        "of the edge's own essential matrix (no depth involved); None: no check. A revisit seen from some metres "
        "behind has a magnified near scene whose flow is underestimated, and the depth-based pose then lands short "
        "of it (bench/RESULTS.md, issue 13, session 2026-12-02 e)",
    )
    pgo_max_scale_disagreement: Optional[float] = Field(
        1.25, gt=1,
        description="leave a loop edge out of the pose graph when its scale measured from both ends (the old "
        "keyframe's depth against the new one's, and the reverse) disagrees by more than this factor: the two "
        "ratios of one consistent measurement multiply to 1. None: no check (and only one direction is measured). "
        "A loop seen on few pixels can put a wrong scale into the whole chain (bench/RESULTS.md, issue 13, "
        "session 2026-12-02 h)")
    pgo_min_pixels: int = Field(30, ge=1, description="minimum confidently matched pixels to trust a loop edge's "
                                "Sim(3) measurement (else the loop is left to the BA alone)")
    final_iters: int = Field(4, ge=0, description="Gauss-Newton iterations per round of the global BA in finalize()")
    final_rounds: int = Field(1, ge=0, description="observe -> global BA rounds in finalize() (re-observing lets "
                              "a learned frontend refine its targets)")
    final_lm: float = Field(1e-5, ge=0, description="multiplicative damping of the global BA")
    final_ep: float = Field(1e-2, ge=0, description="additive damping of the global BA")




class OnlineBAConfig(BAConfigBase):
    """``online_ba``: PV-SLAM's online BA (a sliding-window BA as each keyframe arrives)."""

    window: int = Field(10, ge=1, description="sliding window: the last `window` keyframes have free poses")
    iters: int = Field(3, ge=0, description="Gauss-Newton iterations per step() call (per keyframe update); "
                       "DROID runs 2 per learned update and ~6 updates per keyframe - a classical frontend observes "
                       "once, so more iterations per call are needed (bench/RESULTS.md)")
    final_iters: int = Field(4, ge=0, description="Gauss-Newton iterations of the short global refinement in "
                             "finalize() (0: none)")


class OfflineBAConfig(BAConfigBase):
    """``offline_ba``: DROID-SLAM's schedule (small local BA per keyframe, global BA at the end)."""

    window: int = Field(7, ge=1, description="local window: the last `window` keyframes have free poses")
    final_iters: int = Field(8, ge=0, description="Gauss-Newton iterations per global-BA round in finalize()")
    final_rounds: int = Field(2, ge=0, description="observe -> global BA rounds in finalize() (DROID's backend "
                              "runs 7 + 12 update/BA rounds; a classical frontend needs fewer)")
