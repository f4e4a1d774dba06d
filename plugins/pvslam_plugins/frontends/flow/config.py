"""Configuration of the classical ``flow`` frontend (OpenCV DIS optical flow)."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator

from pvslam_core.config_base import PluginConfig


class FlowFrontendConfig(PluginConfig):
    """DIS optical flow + forward-backward and photometric confidence + panoptic-aware dynamic masking.

    Units: ``*_px`` fields and ``fb_sigma`` are in **full-resolution image pixels** unless they say "BA px"
    (pixels at the bundle-adjustment resolution, 1/``graph.ba_downsample`` of the image).
    """

    # ba_downsample: the BA resolution comes from graph.ba_downsample (BuildContext.ba_downsample)
    renamed = {"eta": "panoptic_offset", "ba_downsample": None}
    # the preset's own DIS iterations and patches (the presets are the choice a user makes)
    retired = {"gradient_descent_iterations": None, "variational_refinement_iterations": None, "patch_size": None,
               "patch_stride": None}

    # --- DIS optical flow -----------------------------------------------------------------------------------
    preset: Literal["ultrafast", "fast", "medium"] = Field(
        "ultrafast",
        description="OpenCV DIS preset for keyframe edges (see finest_scale; the pyramid depth matters more than "
        "the preset on low-texture road).",
    )
    flow_scale: float = Field(
        0.5,
        description="Resolution at which flow is computed, relative to the input image: 1.0 (full) or 0.5.",
    )
    finest_scale: Optional[int] = Field(
        0, ge=0, le=5,
        description="DIS finest pyramid level (0 = the flow resolution itself); None: the preset's own "
        "(ultrafast/fast 2, medium 1). Median target error on the ground of the synthetic driving loop (1-frame gap, "
        "BA px) and relative DIS cost: ultrafast@0.5 fs1 0.20 (1x); ultrafast@0.5 fs0 0.09 (3.2x, default; "
        "keyframe-edge confident-pixel p90 error 0.20 vs 0.30 BA px); medium@0.5 0.12 (2.6x); "
        "fast@1.0 0.15 (2.8x); fast@0.5 fs0 0.07 (6x); medium@1.0 0.06 (8x). Whole driving loop with the robust BA: "
        "ultrafast@0.5 fs0 0.29-0.38 % ATE, medium@1.0 fs1 0.17-0.53 % at about twice the run time.",
    )
    track_preset: Optional[Literal["ultrafast", "fast", "medium"]] = Field(
        None,
        description="DIS preset for the per-frame motion filter (track); None: same as `preset`.",
    )
    track_finest_scale: Optional[int] = Field(
        None, ge=0, le=5,
        description="DIS finest level for track; None: same as `finest_scale`.",
    )
    reuse_track_flow: bool = Field(
        True,
        description="Reuse the flow computed while tracking a frame that becomes a keyframe for its edges to the "
        "previous keyframe (saves one flow pair per keyframe; only as accurate as the track settings, so set it "
        "to false when track uses cheaper settings than the edges).",
    )
    track_velocity_init: bool = Field(
        True,
        description="Start the motion filter's DIS from the previous frame's flows scaled to this frame's gap "
        "(constant velocity) instead of zero. On driving-loop pairs 2-3 frames apart the median error against the "
        "true flow fell from 2.27 to 1.84 flow px with such a prediction (1-frame short).",
    )
    track_init_min_flow: float = Field(
        1.0, ge=0.0,
        description="...only when the predicted mean flow is at least this (BA px); smaller motions are found from "
        "zero, where the prediction only adds the previous flow's noise.",
    )
    flow_threads: int = Field(
        2, ge=1, le=8,
        description="Threads for independent DIS calls (a frame's forward and backward tracking flow, a new keyframe's "
        "edge flows); OpenCV releases the GIL while computing, so with 2 cores they overlap. Results do not depend "
        "on it (lanes.py).",
    )

    # --- targets and confidence -----------------------------------------------------------------------------
    fb_sigma: float = Field(
        1.0, gt=0.0,
        description="Forward-backward consistency scale (full-res px): confidence c = exp(-fb^2 / (2 sigma^2)).",
    )
    texture_tau: float = Field(
        1e-3, ge=0.0,
        description="Texture term of the confidence: lam / (lam + tau) with lam the Shi-Tomasi minimum eigenvalue of "
        "the 5x5 structure tensor (OpenCV's scale: ~1e-4 on fine asphalt at the flow resolution, 1e-3 on facades). "
        "Weak texture (the near road, sky, bare walls, the flanks of buses) gives a flow that DIS gets "
        "consistently wrong in both directions; the forward-backward and photometric checks cannot see it. "
        "0 = off (lam follows the exposure: under auto-exposure ramps the term costs some accuracy, "
        "bench/RESULTS.md).",
    )
    texture_quantile: Optional[float] = Field(
        0.75, gt=0.0, lt=1.0,
        description="With texture_tau: tau is at most this quantile of the image's own lam, so an image whose "
        "texture is weak everywhere (a bare room) keeps relative weights instead of all falling below the "
        "confidence thresholds downstream (None: tau as given).",
    )
    photo_sigma: float = Field(
        4.0, ge=0.0,
        description="Photometric confidence scale (gray levels): the confidence is multiplied by "
        "exp(-r^2 / (2 sigma^2)), r = local mean |I1(x + f) - I0(x)| after removing the global exposure "
        "change (gain and offset, fitted robustly on unsaturated pixels: flow_ops.fit_exposure). Catches flows "
        "that are consistently wrong in both directions (low texture, strong perspective shear). 0 disables.",
    )
    weighted_pooling: bool = Field(
        True,
        description="Average the flow over each BA block weighted by the FB confidence (robust at occlusion "
        "boundaries); False: plain block average. Both are exact for a smooth flow.",
    )

    # --- motion filter and tracking failure -----------------------------------------------------------------
    keyframe_thresh: float = Field(
        2.0, gt=0.0,
        description="New keyframe when the mean flow magnitude to the last keyframe exceeds this (BA px). DROID "
        "uses 2.4 with its learned flow.",
    )
    keyframe_min_coverage: float = Field(
        0.7, ge=0.0, le=1.0,
        description="New keyframe when fewer than this fraction of the last keyframe's pixels are still tracked "
        "(inside the frame and forward-backward consistent). On forward driving many pixels leave the view or "
        "fail long before the mean measured flow grows, so this keeps keyframes overlapping (about every 2nd "
        "frame on the synthetic driving loop at 12 fps).",
    )
    track_recover_fail_fraction: float = Field(
        0.5, gt=0.0, le=1.0,
        description="When more than this fraction of the pixels fail the forward-backward check while tracking, "
        "the flows are computed again from the homography of LK-tracked corners (recover.py: a fast turn moves "
        "the image beyond DIS's coarsest level) and the better of the two is kept; 1.0: never.",
    )
    road_plane: bool = Field(
        True,
        description="Replace DIS's flow on the ground ahead of a car camera by the flow of the road plane's "
        "homography where that explains the image better (road_plane.py): a direct search of the plane's motion "
        "with the map's rotation, for the near road at speed that DIS cannot follow. Off for a hand-held camera "
        "that walks over a floor (the road's depth prior assumes a constant camera height) or to save CPU (~20 % a "
        "frame on the driving loop).",
    )
    road_region: float = Field(
        0.15, gt=0.0, lt=0.5,
        description="With road_plane: the searched rows start this fraction of the image height below the "
        "principal point (the ground well ahead of a level camera).",
    )
    road_max_gap: int = Field(
        5, ge=0,
        description="With road_plane: keyframe pairs further apart (frames) keep DIS's flow. The plane's flow has "
        "no forward-backward check (both directions come from one homography), and far apart the ground left in "
        "view is a thin band near the horizon where sidewalks and building bases pass for road.",
    )
    road_verify: bool = Field(
        True,
        description="With road_plane: weigh each plane pixel by DIS's residual between the views aligned by the "
        "merged flow (two more DIS calls per pair) instead of the texture term (road_frontend.py).",
    )
    road_margin: float = Field(
        1.1, gt=0.0, le=2.0,
        description="With road_plane: a pixel takes the plane's flow where its 5x5 brightness residual is below "
        "this factor times DIS's.",
    )
    road_depth_weight: float = Field(
        1.0, ge=0.0,
        description="With road_plane and road_verify (without either it does nothing; both on by default): "
        "weight alpha0 of a BA prior on each keyframe's inverse depth d at its verified "
        "plane pixels, alpha0 (d - dp)^2 / dp^2 with dp = (y - cy) / (fy h), the road's at one camera height h for "
        "the whole run, set once the map's road depth and its motion agree on it (road_frontend.py); 0: off.",
    )
    road_distance_weight: float = Field(
        100.0, ge=0.0,
        description="With road_plane: weight (flow-cost units of the relative error) of a BA prior on the distance "
        "between consecutive keyframes, the road's translation between them in camera heights (chained from the "
        "tracking's plane motions) times one camera height in map units, measured once from the map's motion over "
        "the road's (road_frontend.py, pvslam_core/geometry/ba_distance.py); 0: off.",
    )
    track_predict_recover: bool = Field(
        True,
        description="When the corners' homography does not recover a failing track, DIS also starts from the image "
        "motion predicted at constant rate (each tracked frame's flow summarised by a homography and chained; "
        "recover.MotionPredictor): a fast turn over a scene with few corners.",
    )
    track_predict_init: bool = Field(
        True,
        description="On a frame without a velocity init (the first after a keyframe, mostly), DIS also starts from "
        "the motion predicted at constant rate when it is at least track_init_min_flow, and the flow with fewer "
        "forward-backward failures is kept: a fast pan that DIS from zero finds only in part.",
    )
    min_texture_std: float = Field(
        2.0, ge=0.0,
        description="Tracking failure when the grayscale intensity std of a frame is below this (black/blank frame).",
    )
    fb_fail_px: float = Field(
        3.0, gt=0.0, description="A pixel fails the forward-backward check when fb > this (full-res px)."
    )
    max_fb_fail_fraction: float = Field(
        0.8, gt=0.0, le=1.0,
        description="Tracking failure (sudden jump) when more than this fraction of pixels fail the FB check or "
        "leave the image.",
    )

    # --- long-baseline edges --------------------------------------------------------------------------------
    use_reprojection_init: bool = Field(
        True,
        description="Initialise DIS with the flow induced by the current poses/depths (graph reprojection) for "
        "long-baseline edges (proximity/loop edges); makes large displacements work.",
    )
    init_min_flow: float = Field(
        1.0, ge=0.0,
        description="Use the reprojection init only when the predicted mean flow exceeds this (BA px).",
    )
    init_compare_min_gap: int = Field(
        4, ge=1,
        description="For edges whose keyframe indices differ by at least this (proximity/loop edges, where the "
        "estimate may be off), also run DIS from zero and keep the result with the higher mean FB confidence. "
        "Closer edges trust the reprojection init.",
    )

    # --- dynamic masking (panoptic-aware confidence) --------------------------------------------------------
    dynamic_masking: bool = Field(
        True,
        description="From an edge's second observation on, pixels whose target disagrees with the reprojection under "
        "the current estimate are dynamic; segment vote; PV-SLAM eq. 4 weights.",
    )
    rounds: int = Field(
        1, ge=1, le=4,
        description="observe -> BA rounds per new keyframe (Frontend.rounds). With 1, a new edge's "
        "dynamic mask is first applied at the next keyframe's BA (edges stay in the window for several keyframes); "
        "2 applies it at once at twice the BA cost.",
    )
    dynamic_updates: int = Field(
        3, ge=1,
        description="Re-estimate an edge's dynamic mask on this many of its observations after the first (each "
        "re-estimate reprojects the edge); later observations keep the last mask.",
    )
    dynamic_thresh: float = Field(
        1.0, gt=0.0, description="Reprojection residual (BA px) above which a pixel is dynamic."
    )
    dynamic_rel_thresh: float = Field(
        3.0, ge=0.0,
        description="The threshold is also at least this multiple of the edge's median residual (robust to a "
        "not-yet-converged estimate); 0 disables.",
    )
    max_dynamic_fraction: float = Field(
        0.8, gt=0.0, le=1.0,
        description="If more than this fraction of an edge's pixels would be dynamic, the estimate (not the scene) "
        "is wrong: the edge gets no dynamic mask. Not lower: a vehicle close to the camera can fill more than half "
        "of the view, and an edge that drops its mask then hands the pose to the vehicle.",
    )
    dynamic_regions: bool = Field(
        True,
        description="Group the dynamic candidates into coherent regions (8-connected, at least dynamic_min_area BA "
        "px, grown by dynamic_grow): a moving vehicle is a region, isolated pixels are left to the robust kernel. "
        "With a segmenter the regions are OR-ed with the segment vote (dynamic.py).",
    )
    depth_check: float = Field(
        0.0, ge=0.0,
        description="Also a candidate: a pixel whose inverse depth, moved from its keyframe into the other one, "
        "differs from that keyframe's own estimate by more than this x its median inverse depth (dynamic.py, "
        "depth_candidates: vehicles moving along the camera's direction are epipolar-consistent, the residual "
        "test cannot see them). 0 = off.",
    )
    dynamic_persist: bool = Field(
        False,
        description="A keyframe keeps the mask it inherited from its reference (moved along the tracked flow) OR-ed "
        "into every later judgement of its edges: once seen moving, a vehicle stays masked while tracked, also on "
        "the edges where it is epipolar-consistent (dynamic_masking.py). Off by default: mixed on the tune seeds "
        "(better on the busy street, worse on moving_vehicles; bench/RESULTS.md, moving objects).",
    )
    dynamic_min_area: int = Field(4, ge=1, description="Smallest dynamic region kept (BA px).")
    dynamic_grow: int = Field(1, ge=0, description="Dynamic regions are dilated by this many BA px.")
    dynamic_track: bool = Field(
        True,
        description="Apply the reference keyframe's dynamic mask (judged from its edges after its first BA, else moved "
        "from the previous keyframe's) to the motion filter's weights, which place the non-keyframes.",
    )
    panoptic_offset: float = Field(10.0, ge=0.0, description="PV-SLAM eq. 4 logit offset (the paper's eta).")
    convention: Literal["paper", "pvo_code"] = Field(
        "paper", description="Mask convention of eq. 4 (see pvslam_core.slam.confidence); keep 'paper'."
    )
    vote_thresh: float = Field(
        0.5, ge=0.0, le=1.0,
        description="A segment becomes dynamic when more than this fraction of its pixels is dynamic.",
    )
    things_only: bool = Field(
        True, description="Only movable thing segments (cars, people) vote, each keyframe's own (segment ids are "
        "unique within a frame only); stuff keeps per-pixel masks.")
    vote_keeps_candidates: bool = Field(
        True,
        description="With a segmenter and dynamic_regions: also keep every raw residual candidate pixel outside the "
        "voted segments (PVO's segm_filter; segments vote over all their pixels). False: voted movable segments "
        "(voting over their judged pixels) OR the coherent regions, the same per-pixel evidence as without a "
        "segmenter (dynamic_masking.py; worse on the moving-vehicles tune seeds: bench/RESULTS.md).",
    )

    # --- the map-independent epipolar cue (epipolar_cue.py) ----------------------------------------------------
    epipolar_cue: bool = Field(
        False,
        description="When a keyframe without a segmentation is added, fit the essential matrix of its tracked flow "
        "from the previous keyframe by RANSAC (the static majority's motion, independent of the map), and again on "
        "its first edges (epipolar_edges); pixels off their epipolar line or moving towards the epipole (negative "
        "depth), grouped into regions, are dynamic on every edge of those keyframes and in tracking "
        "(epipolar_cue.py, dynamic_masking.py). Catches crossing, turning and overtaking vehicles before they drag "
        "the map: worth turning on for streets with large moving vehicles and no segmenter; off by default because "
        "its false positives cost accuracy on static scenes (bench/RESULTS.md, issue 13).",
    )
    epipolar_track: bool = Field(
        False,
        description="With epipolar_cue, also judge every tracked frame's flow from the last keyframe by the epipolar "
        "cue and mask its outlier regions in the weights that place the frame (the keyframe then reuses the "
        "judgement); a fit per frame instead of per keyframe. Like the keyframe cue, not on segmented keyframes "
        "unless epipolar_with_segmenter.",
    )
    epipolar_with_segmenter: bool = Field(
        False,
        description="Also run the epipolar cue on keyframes that have a segmentation (then OR-ed with the segment "
        "vote). Off: the cue is for runs without a segmenter (with one it cost accuracy on the default driving "
        "loop: bench/RESULTS.md).",
    )
    epipolar_replaces_residual: bool = Field(
        False,
        description="With epipolar_cue and no segmenter, the cue alone marks the dynamic pixels of the edges (no "
        "residual test against the current estimate, which flags the static scene as often as the movers once a "
        "mover has dragged that estimate). Off: both OR-ed. With a segmenter the residual test always feeds the "
        "vote.",
    )
    epipolar_edges: int = Field(
        2, ge=0,
        description="Epipolar cue: also fit and judge the new keyframe's edges to this many nearest older keyframes "
        "when their flow is computed (longer baselines than the tracked flow); 0 = the tracked flow only.",
    )
    epipolar_thresh: float = Field(
        0.5, gt=0.0, description="Epipolar cue: Sampson distance (BA px) above which a pixel is a candidate."
    )
    epipolar_rel: float = Field(
        3.0, ge=0.0, description="Epipolar cue: the threshold is at least this x the inliers' median distance."
    )
    epipolar_back: float = Field(
        0.5, gt=0.0,
        description="Epipolar cue: a candidate when its parallax points towards the epipole by more than this (BA "
        "px): a negative depth, no static point.",
    )
    epipolar_min_conf: float = Field(
        0.05, ge=0.0, le=1.0,
        description="Epipolar cue: only pixels whose flow confidence exceeds this are fitted and judged (a mover's "
        "flow often half fails the forward-backward check yet keeps some weight in the BA: 0.5 judged too few).",
    )
    epipolar_ransac_px: float = Field(0.25, gt=0.0, description="Epipolar cue: RANSAC inlier threshold (BA px).")
    epipolar_min_parallax: float = Field(
        0.05, ge=0.0,
        description="Epipolar cue: no mask when the inliers' median parallax is below this (BA px; a stopped "
        "camera has no epipolar geometry).",
    )

    @field_validator("flow_scale")
    @classmethod
    def _check_scale(cls, v: float) -> float:
        if v not in (1.0, 0.5):
            raise ValueError(f"flow_scale must be 1.0 or 0.5, got {v}")
        return v
