"""Pipeline configuration: pydantic v2 models, TOML files, ``--set`` overrides and ablation files.

A pipeline config is a TOML file whose tables are the pipeline's components and sections::

    [dataset]                 # every component is {plugin = "name", ...the plugin's own parameters}
    plugin = "synthetic"
    scenario = "driving_loop"

    [loop]
    plugin = "none"           # optional components (segmenter, loop, vps) can be switched off

Component parameters are validated by the selected plugin's own config model (``extra="forbid"``).  Every error
names the file, the key path and the allowed values.  ``resolve()`` fills in every default and returns a
:class:`ResolvedConfig`; its ``to_json()`` is what each run directory stores, and loading that JSON back through
these models gives an identical resolved config.
"""
from __future__ import annotations

import copy
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal, Optional

from pydantic import BaseModel, Field, ValidationError, field_validator, model_serializer, model_validator

from .config_base import PluginConfig

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the same parser as the `tomli` package (a dependency there)
    import tomli as tomllib

LOG = logging.getLogger("pvslam.config")

COMPONENTS = ("dataset", "segmenter", "frontend", "loop", "optimizer", "vps")
OPTIONAL_COMPONENTS = ("segmenter", "loop", "vps")
DISABLED = "none"


class ConfigError(ValueError):
    """A configuration problem; the message names the source, the key path and what is allowed."""


class Component(BaseModel):
    """``{plugin = "name", **params}``; params are validated later by the plugin's own model."""

    model_config = {"extra": "forbid"}
    plugin: str = Field(..., description="name of the plugin (see `pvslam plugins`); 'none' switches an optional one off")
    params: dict[str, Any] = Field(default_factory=dict, description="the plugin's parameters (its own config model)")

    @model_validator(mode="before")
    @classmethod
    def _split(cls, data: Any) -> Any:
        if isinstance(data, str):
            return {"plugin": data, "params": {}}
        if isinstance(data, dict) and "params" not in data:
            if "plugin" not in data:
                raise ValueError("missing key 'plugin' (the name of the plugin to use)")
            rest = {k: v for k, v in data.items() if k != "plugin"}
            return {"plugin": data["plugin"], "params": rest}
        return data

    @model_serializer(mode="plain")
    def _flat(self) -> dict[str, Any]:
        return {"plugin": self.plugin, **self.params}

    @property
    def enabled(self) -> bool:
        return self.plugin != DISABLED


class RunSection(PluginConfig):
    """Where a run writes, on which device, with which seed and threads."""

    name: str = Field("run", description="run name; the run directory is <output_dir>/<name>-<timestamp>")
    output_dir: str = Field("runs", description="folder that holds run directories (relative to the current directory)")
    device: str = Field("cpu", description="torch device for the pipeline's tensors: cpu, cuda, cuda:0, ...")
    seed: int = Field(0, description="seed of torch, numpy and OpenCV's RANSAC: a run is deterministic for a seed")
    threads: int = Field(1, ge=0, description="torch CPU threads (0 = torch's default); the BA's tensors are small, "
                                             "one thread avoids contention on small machines")
    progress: bool = Field(True, description="show progress bars (only on a terminal)")
    max_frames: Optional[int] = Field(None, ge=1, description="stop after this many input frames")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field("INFO", description="log level of log.txt")
    checkpoint_every: int = Field(20, ge=1, description="rewrite the trajectory files every N keyframes")
    read_ahead: int = Field(2, ge=0, description="frames read and decoded ahead on a background thread (0: none); "
                            "decoding overlaps the mapping on a second core, memory stays bounded")
    keep_freed_memory: bool = Field(True, description="Linux/glibc: keep freed memory in the process for reuse "
                                    "instead of re-faulting it on every BA call (less CPU); process-wide, set once "
                                    "(docs/decisions.md: run.keep_freed_memory)")
    write_behind: int = Field(4, ge=0, description="panoptic PNG writes queued to a background thread (0: written "
                              "in the pipeline thread); a write error still stops the run, one frame later")

    @field_validator("name")
    @classmethod
    def _one_folder_name(cls, v: str) -> str:
        from .rundir import check_name  # the run directory is <output_dir>/<name>-<timestamp>: it must stay inside

        return check_name(v)


class GraphSection(PluginConfig):
    """Keyframe and edge policy of the frame graph (DROID-SLAM style; anchors 1.5)."""

    ba_downsample: int = Field(8, ge=1, description="BA resolution = image size / ba_downsample")
    ba_min_focal: float = Field(
        24.0, ge=0, description="unless graph.ba_downsample is set explicitly, it is halved (8 -> 4 -> 2 -> 1) while "
        "the focal length at BA resolution, min(fx, fy) / ba_downsample in BA pixels per radian, would be below this: "
        "every threshold in BA pixels was chosen at 272 / 8 = 34 (the 320x240 synthetic camera), and a flow in BA "
        "pixels is that focal length times an angle; 24 ~ 34 / sqrt(2) halves where that lands nearer 34 (160x120: 17 "
        "-> 34) and keeps 1/8 on KITTI at half size (44); 0 = never (pvslam_core/adapt.py)")
    # ba_min_rows (a row count) was replaced by ba_min_focal: run directories' config.json that still carry it load,
    # with a warning, and the focal rule applies
    renamed: ClassVar[dict[str, Any]] = {"ba_min_rows": None}
    warmup: int = Field(5, ge=2, description="keyframes collected before the map is initialised")
    warmup_seconds: float = Field(
        0.65, ge=0, description="...or fewer (at least 3) once they span this many seconds of video (0: off). A slow "
        "camera over a textureless room made its 5th keyframe only 1.4-2.1 s into the motion; on the 10-12 frames/s "
        "driving sequences (a keyframe every ~2 frames) 5 keyframes come first (pvslam_core/slam/bootstrap.py)")
    init_min_parallax_deg: float = Field(
        0.5, gt=0, description="two-view initialisation needs at least this parallax (degrees, at "
        "graph.init_parallax_quantile of its points); KITTI 01's "
        "highway frames give 0.7-0.8 deg between nearby keyframes (far, forward-looking points)")
    init_parallax_quantile: float = Field(
        0.75, gt=0, lt=1, description="...at this quantile of the pair's triangulated points' parallax (0.5: the "
        "median). With graph.init_chain_tol the near road of a fast forward drive, which gave the pair its "
        "parallax, is removed as unmatched, and the far field and the focus of expansion hold the median down "
        "(pvslam_core/slam/initializer.py, bench/RESULTS.md)")
    init_relative_confidence: bool = Field(
        True, description="two-view initialisation counts a correspondence as confident above half of the pair's "
        "90th-percentile weight (at most 0.5, at least initializer.RELATIVE_FLOOR = 0.05) instead of above 0.5 "
        "(false): a frontend whose weights sit lower, such as the flow frontend with its texture term, would "
        "otherwise start the map seconds late")
    init_chain_tol: float = Field(
        1.0, ge=0, description="two-view initialisation keeps a correspondence of its pair (a, m) only where the "
        "flows of the keyframes between, chained a -> a+1 -> ... -> m, stay in view and land within this many BA "
        "px of it (0: off). On a fast forward drive the near road leaves the view within the pair, yet its flow "
        "passes the forward-backward check and corrupts the two-view choice; with the check the parallax is read "
        "at graph.init_parallax_quantile (pvslam_core/slam/bootstrap.py, bench/RESULTS.md)")
    init_chain_fallback: bool = Field(
        True, description="with graph.init_chain_tol: when the direct flow of a pair keeps fewer confident "
        "correspondences than the initialisation needs, the pair's correspondences are its links' chained flows "
        "instead. Before the map exists nothing starts a direct flow from the motion, and DIS from zero loses a "
        "pair a few keyframes apart when the image moves fast (a 45 deg lens on a hand-held camera: pvslam_core/"
        "slam/bootstrap.py, bench/RESULTS.md)")
    unobserved_weight: float = Field(
        0.3, gt=0, le=1, description="confidence factor, in the window BA (and a new keyframe's motion-only pose "
        "guess when it keeps every pixel), of the depth pixels no edge with parallax has measured yet (a new "
        "keyframe's filled holes; 1: off; pvslam_core/slam/observed.py, bench/RESULTS.md)")
    guess_min_measured: float = Field(
        0.5, ge=0, le=1, description="a new keyframe's motion-only pose guess uses only the measured depth pixels of "
        "its reference (graph.unobserved_weight) when they are at least this fraction of its tracked pixels (1: "
        "never)")
    second_start: bool = Field(
        True, description="when the two keyframes before a new one are mostly unmeasured (below "
        "graph.guess_min_measured: after a pan), run its window BA also from its centre at constant velocity from "
        "the last measured keyframes and keep the lower flow cost (pvslam_core/slam/motion_start.py)")
    second_start_span: float = Field(0.25, gt=0, description="seconds between the two measured keyframes whose "
                                     "motion graph.second_start continues")
    second_start_horizon: float = Field(1.0, gt=0, description="graph.second_start predicts at most this many "
                                        "seconds past the last measured keyframe")
    observed_parallax: float = Field(
        1.0, ge=0, description="translation-only flow (BA px) an edge must give a pixel of its source keyframe to "
        "count its depth as measured (graph.unobserved_weight; a pixel farther than the keyframe's median depth is "
        "read at the median)")
    init_ambiguity_ratio: float = Field(
        3.0, ge=0, description="two-view initialisation declines a pair (and waits for the next) when the chosen "
        "motion, the best fit among those with most points in front, fits this many times worse (truncated Sampson "
        "cost) than another with enough points in front (the initialiser's min_inliers, 60): with little parallax "
        "a forward drive's points near the focus of expansion fall behind by noise, and a sideways motion wins "
        "(0: off; pvslam_core/slam/initializer.py, bench/RESULTS.md)")
    init_tie_ratio: float = Field(
        1.25, ge=0, description="two-view initialisation declines a pair (and waits for the next) when another motion "
        "with >= 90 % of the chosen one's points in front fits within this factor of its cost and heads more than "
        "20 deg away: the pair cannot tell them apart (0: off; pvslam_core/slam/initializer.py)")
    init_tries: int = Field(3, ge=1, description="two-view initialisation pairs tried per new keyframe, all ending "
                            "at the newest: from the window's first keyframe, from the middle, from two back (fast "
                            "motion breaks the flow of the farthest pair; pvslam_core/slam/bootstrap.py)")
    init_window: int = Field(
        8, ge=1, description="the first view of an initialisation pair is at most this many keyframes before the "
        "newest (a sliding window: a hand-held camera that turned away never overlaps the fragment's first "
        "keyframe again; pvslam_core/slam/bootstrap.py)")
    neighbours: int = Field(3, ge=1, description="edges to the previous `neighbours` keyframes of each new keyframe")
    proximity_window: int = Field(25, ge=0, description="look back this many keyframes for proximity edges")
    proximity_thresh: float = Field(16.0, gt=0, description="max frame distance (BA px) for a proximity edge")
    proximity_nms: int = Field(1, ge=0, description="suppress proximity edges within this index distance of another")
    max_proximity_edges: int = Field(2, ge=0, description="proximity edges added per new keyframe")
    active_window: int = Field(10, ge=2, description="edges touching the last N keyframes are observed in each update")
    remove_redundant: bool = Field(True, description="drop a keyframe that is too close to its predecessor")
    redundant_thresh: float = Field(1.5, ge=0, description="frame distance (BA px) under which a keyframe is redundant")
    redundant_max_flow: float = Field(
        4.0, ge=0, description="...and the 90th percentile of the same per-pixel distance must also be under this "
        "(BA px; 0: the mean alone): where most of the image is far (a wide street, a highway) the mean stays small "
        "while the near field moves several BA px, and keyframes 13 m apart were judged redundant "
        "(pvslam_core/slam/keyframing.py)")
    fill_row_min_frac: float = Field(
        0.25, ge=0, le=1, description="a new keyframe's depth is the previous one's moved into it; a row with at "
        "least this fraction of its pixels known fills its holes with its own median, the others with the image's "
        "(0: the image's median everywhere; pvslam_core/geometry/projective.py fill_holes)")
    max_keyframe_gap_s: float = Field(
        0.5, gt=0, description="a keyframe whose removal would leave more than this many seconds between the "
        "keyframes around it is never redundant, whatever the estimate says (ORB-SLAM keeps one at least every "
        "second): when the estimate "
        "underrates the motion (a far scene, a textureless road) the frame distance stays small and the kept "
        "keyframes were 38 m apart on the synthetic street, with the scale collapsing in between")
    provisional_keyframes: bool = Field(
        True, description="a new keyframe whose frame distance to the last one (under its motion-only pose guess) is "
        "below redundant_thresh stays provisional: the tracking reference of the next frames, but no edges, BA or "
        "loop query until the next keyframe removes it (still redundant) or makes it an ordinary one. About half "
        "the driving loop's keyframes used to pay for edges and a BA and then be removed as redundant")
    reinit_after: int = Field(4, ge=1, description="consecutive failed frames before the map is re-initialised")
    max_active_edges: int = Field(
        256, ge=8, description="cap on active edges: beyond it the oldest edges not touching the newest keyframe "
        "retire (their last observations stay for the final BA). Edges also retire when they no longer touch the "
        "last `active_window` keyframes, which normally keeps far fewer active")
    retired_margin: Optional[int] = Field(
        None, ge=0, description="window BAs also use the last observations of retired edges whose both ends are at "
        "most this many keyframes before the active window, as frozen constraints (DROID-SLAM's inactive edges, "
        "t0 - 3; 3 there); None: only active edges. Helps a fast forward drive's scale, costs others (bench/RESULTS.md)")
    max_edge_age: int = Field(
        25, ge=1, description="an edge retires after taking part in this many optimisation rounds (DROID-SLAM's "
        "frontend max_age)")
    bidirectional: bool = Field(True, description="add edges in both directions")
    motion_robust: Optional[Literal["none", "huber", "cauchy"]] = Field(
        "cauchy", description="robust kernel of the motion-only BA that places non-keyframes and guesses new "
        "keyframe poses ('none': least squares)")
    motion_robust_scale: float = Field(1.0, gt=0, description="its scale in BA-resolution pixels")
    proximity_max_flow: float = Field(
        8.0, ge=0, description="keep a proximity edge only when the 90th percentile of its induced "
        "translation-only flow (the parallax; both directions, BA px, under the current estimate) is at most this; "
        "0: no limit. Proximity edges are chosen on "
        "the mean flow, and a forward-driving camera's keyframes 4-25 back qualify while the near road between them "
        "moves 10-50 BA px, which DIS does not find but reports as consistent: on the synthetic moving_vehicles "
        "street those edges made the scale grow 2x over 200 frames (pvslam_core/slam/keyframing.py)")


class LoopClosureSection(PluginConfig):
    """Which loop candidates close a loop (the one loop policy; see :mod:`pvslam_core.slam.loops`)."""

    accept_unverified: bool = Field(
        True, description="accept candidates the detector did not verify geometrically (verified = None: a "
        "retrieval-only detector, accepted on its similarity score); candidates that failed verification are never "
        "accepted")
    consecutive: int = Field(
        1, ge=1, description="require candidates to the same place from this many consecutive keyframes (DPVO uses 3)")
    consecutive_tolerance: int = Field(
        3, ge=0, description="keyframe slack when checking that consecutive candidates point at the same place")
    nms_keyframes: int = Field(
        5, ge=0, description="skip a candidate (i, j) when an accepted loop (i', j') from an earlier keyframe has "
        "|i - i'| <= n and |j - j'| <= n, in keyframe indices (0 disables); detectors use it to skip verification")
    max_rotation_deg: float = Field(
        60.0, gt=0, le=180,
        description="reject a loop whose two keyframes' current orientations differ by more than this (look-alike "
                    "places seen from opposite directions); rotation drift is far smaller than this")
    ba_min_gap: int = Field(
        8, ge=0, description="a loop accepted fewer than this many keyframes after the last loop BA only adds its "
        "edges (the window BA uses them); on repeated laps nearly every keyframe closes a loop and a loop BA each "
        "made later frames 2x slower")


class OutputsSection(PluginConfig):
    """What a run writes besides its trajectory (see ``pvslam_core/outputs``)."""

    trajectory_kitti: bool = Field(False, description="also write trajectory_kitti.txt (KITTI's 3x4 pose rows)")
    ply: bool = Field(True, description="write cloud_rgb.ply and cloud_panoptic.ply")
    # A monocular map's scale is arbitrary: every cloud filter is relative (see pvslam_core/outputs/cloud.py).
    ply_depth_factor: Optional[float] = Field(
        3.0, gt=0, description="drop points farther than this x their keyframe's median depth (None: keep far points)")
    ply_min_views: int = Field(
        1, ge=0, description="keep a pixel only when at least this many neighbouring keyframes see its point at "
        "their own depth (multi-view consistency; 0: off)")
    ply_drop_categories: list[str] = Field(
        default_factory=lambda: ["sky"], description="panoptic category names never put in the clouds")
    ply_voxel: float = Field(
        0.0, ge=0, description="voxel downsampling: voxel edge as a fraction of the map's median keyframe depth "
        "(0: off; e.g. 0.01)")
    keyframe_depth: bool = Field(
        True, description="write keyframes/NNNNNN_depth.npy (z-depth, map units) and keyframes/keyframes.json")
    panoptic_png: bool = Field(True, description="write per-frame panoptic PNGs (COCO id encoding)")
    panoptic_vis: bool = Field(False, description="also write colour visualisations of the panoptic ids")
    plots: bool = Field(True, description="write plots of the trajectory and its error")

    # ply_max_depth was an absolute depth in map units; a monocular map's scale is arbitrary, so it removed nothing
    # (or everything): files that still set it load, with a warning, and ply_depth_factor applies instead.
    renamed: ClassVar[dict[str, Any]] = {"ply_max_depth": None}
    # the depth-edge and multi-view tests' settings are constants of pvslam_core/outputs/cloud.py
    retired: ClassVar[dict[str, Any]] = {"ply_edge_ratio": 1.5, "ply_neighbours": 2, "ply_consistency": 0.05}


class EvaluationSection(PluginConfig):
    """The end-of-run evaluation against ground truth (``pvslam eval`` recomputes it)."""

    enabled: bool = Field(True, description="evaluate against ground truth at the end of the run when it exists")
    align: Literal["sim3", "se3", "none"] = Field("sim3", description="trajectory alignment for ATE (sim3 for monocular)")
    rpe_delta: int = Field(1, ge=1, description="RPE frame offset: frames between the two poses of each relative motion")
    vpq_ks: list[int] = Field(default_factory=lambda: [0, 5, 10, 15], description="VPQ window sizes k (frames); VPQ "
                              "averages over them")
    loop_tolerance: int = Field(5, ge=0, description="frames of tolerance when matching detected loops to GT revisits")
    max_panoptic_frames: int = Field(300, ge=1, description="evaluate PQ/VPQ on at most this many frames (memory)")


class PipelineConfig(PluginConfig):
    run: RunSection = Field(default_factory=RunSection, description="run name, folder, device, seed, threads")
    dataset: Component = Field(default_factory=lambda: Component(plugin="synthetic"),
                               description="the input reader (or the built-in generator)")
    segmenter: Component = Field(default_factory=lambda: Component(plugin="labels"),
                                 description="panoptic segmentation of each frame (optional)")
    frontend: Component = Field(default_factory=lambda: Component(plugin="flow"),
                                description="correspondences and confidences between keyframes")
    loop: Component = Field(default_factory=lambda: Component(plugin="classical"),
                            description="loop-closure candidates (optional)")
    optimizer: Component = Field(default_factory=lambda: Component(plugin="online_ba"),
                                 description="the bundle adjustment of poses and depths")
    vps: Component = Field(default_factory=lambda: Component(plugin="warp_iou"),
                           description="video panoptic segmentation: ids consistent over time (optional)")
    graph: GraphSection = Field(default_factory=GraphSection)
    loop_closure: LoopClosureSection = Field(default_factory=LoopClosureSection)
    outputs: OutputsSection = Field(default_factory=OutputsSection, description="what the run directory gets")
    evaluation: EvaluationSection = Field(default_factory=EvaluationSection,
                                          description="evaluation against ground truth at the end of the run")

    #: keys that moved between tables: old "table.key" -> new "table.key" (kept for one release, with a warning)
    moved: ClassVar[dict[str, str]] = {
        "graph.loop_max_rotation_deg": "loop_closure.max_rotation_deg",
        "graph.loop_ba_min_gap": "loop_closure.ba_min_gap",
        "loop.consecutive": "loop_closure.consecutive",
        "loop.consecutive_tolerance": "loop_closure.consecutive_tolerance",
        "loop.nms_keyframes": "loop_closure.nms_keyframes",
    }

    @model_validator(mode="before")
    @classmethod
    def _moved_keys(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        out = None
        for old, new in cls.moved.items():
            (ot, ok), (nt, nk) = old.split("."), new.split(".")
            table = data.get(ot)
            if not isinstance(table, dict) or ok not in table:
                continue
            if out is None:
                out = copy.deepcopy(data)
            value = out[ot].pop(ok)
            dest = out.setdefault(nt, {})
            if isinstance(dest, dict) and nk not in dest:
                dest[nk] = value
            LOG.warning("config key %s is deprecated; use %s", old, new)
        return data if out is None else out


# --------------------------------------------------------------------------------------------- raw dicts ----
def read_config_text(path: str | Path) -> str:
    """The text of a config file; a folder, a missing file or bytes that are not UTF-8 are clear errors."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{p}: is a directory, not a config file (give the .toml or config.json inside it)")
    if not p.is_file():
        raise ConfigError(f"{p}: config file not found")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the config file: {exc.strerror or exc}") from exc
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ConfigError(f"{p}: not UTF-8 text: byte 0x{data[exc.start]:02x} on line {line} (offset {exc.start}); "
                          "config files must be saved as UTF-8") from None


def read_toml(path: str | Path) -> dict[str, Any]:
    p = Path(path)
    text = read_config_text(p)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from exc


def parse_value(text: str) -> Any:
    """A ``--set`` value: TOML syntax when it parses (numbers, booleans, arrays, quoted strings), else a string;
    ``null`` is None (TOML has no null, and an optional key set in a config file must be unsettable; ``none`` stays
    a string: it is a plugin name)."""
    if text.strip() == "null":
        return None
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_override(item: str) -> tuple[str, Any]:
    if "=" not in item:
        raise ConfigError(f"--set {item!r}: expected KEY.PATH=VALUE, e.g. --set loop.plugin=none")
    key, value = item.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise ConfigError(f"--set {item!r}: empty key path")
    return key, parse_value(value.strip())


def apply_overrides(raw: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Apply dotted-key overrides (``{"frontend.preset": "fast"}``) to a copy of ``raw``."""
    out = copy.deepcopy(raw)
    for key, value in overrides.items():
        parts = key.split(".")
        node = out
        for part in parts[:-1]:
            nxt = node.get(part)
            if isinstance(nxt, str) and part in COMPONENTS:  # `dataset = "kitti"` shorthand
                nxt = {"plugin": nxt}
            if nxt is None:
                nxt = {}
            if not isinstance(nxt, dict):
                raise ConfigError(f"override {key}: {part!r} is a value, not a table")
            node[part] = nxt
            node = nxt
        node[parts[-1]] = value
    return out


# ------------------------------------------------------------------------------------------ validation ----
def _allowed_at(model: type[BaseModel], loc: tuple) -> Optional[list[str]]:
    """Field names of the (sub)model that ``loc`` points into, for 'allowed values' in error messages."""
    cur: Any = model
    for part in loc:
        if isinstance(cur, type) and issubclass(cur, BaseModel) and isinstance(part, str) and part in cur.model_fields:
            ann = cur.model_fields[part].annotation
            cur = ann
        else:
            break
    if isinstance(cur, type) and issubclass(cur, BaseModel):
        return list(cur.model_fields)
    return None


def format_validation_error(exc: ValidationError, source: str, model: type[BaseModel], prefix: str = "") -> str:
    lines = [f"{source}: invalid configuration"]
    for err in exc.errors():
        loc = tuple(p for p in err["loc"] if p not in ("params",))
        path = ".".join(str(p) for p in ((prefix,) if prefix else ()) + loc) or "(top level)"
        if err["type"] == "extra_forbidden":
            allowed = _allowed_at(model, loc[:-1])
            msg = f"unknown key {path!r}"
            if allowed is not None:
                msg += "; allowed keys here: " + ", ".join(allowed)
        else:
            msg = f"{path}: {err['msg']}"
            if "input" in err and err["type"] not in ("missing",):
                msg += f" (got {err['input']!r})"
        lines.append("  " + msg)
    return "\n".join(lines)


def _default_plugins(raw: dict[str, Any]) -> dict[str, Any]:
    """A component table without ``plugin`` keeps the default plugin: ``[frontend] preset = "fast"``."""
    out = dict(raw)
    for name in COMPONENTS:
        if isinstance(out.get(name), dict) and "plugin" not in out[name]:
            default = PipelineConfig.model_fields[name].default_factory().plugin
            out[name] = {"plugin": default, **out[name]}
    return out


def validate_pipeline(raw: dict[str, Any], source: str = "<config>") -> PipelineConfig:
    raw = _default_plugins(raw)
    try:
        return PipelineConfig.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, PipelineConfig)) from None


@dataclass
class ResolvedConfig:
    """A validated pipeline config with every plugin's parameters parsed by that plugin's model."""

    pipeline: PipelineConfig
    models: dict[str, Optional[BaseModel]] = field(default_factory=dict)  # interface -> plugin config (None = off)
    source: str = "<config>"

    def to_dict(self) -> dict[str, Any]:
        data = self.pipeline.model_dump(mode="json")
        for name in COMPONENTS:
            model = self.models.get(name)
            data[name] = {"plugin": getattr(self.pipeline, name).plugin}
            if model is not None:
                data[name].update(model.model_dump(mode="json"))
        return data

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=False)


def resolve(pipeline: PipelineConfig, registry=None, source: str = "<config>") -> ResolvedConfig:
    """Validate each component's params with its plugin's config model (filling defaults)."""
    from .registry import PluginError, get_registry

    registry = registry or get_registry()
    models: dict[str, Optional[BaseModel]] = {}
    for name in COMPONENTS:
        comp: Component = getattr(pipeline, name)
        if not comp.enabled:
            if name not in OPTIONAL_COMPONENTS:
                raise ConfigError(
                    f"{source}: {name}.plugin cannot be 'none' (only {', '.join(OPTIONAL_COMPONENTS)} can be switched off)"
                )
            if comp.params:
                raise ConfigError(f"{source}: {name} is switched off (plugin = 'none') but has parameters: "
                                  + ", ".join(comp.params))
            models[name] = None
            continue
        try:
            spec = registry.get(name, comp.plugin)
        except PluginError as exc:
            raise ConfigError(f"{source}: {name}.plugin: {exc}") from None
        try:
            models[name] = spec.config_model.model_validate(comp.params)
        except ValidationError as exc:
            raise ConfigError(
                format_validation_error(exc, source, spec.config_model, prefix=name)
                + f"\n  ({name} plugin {comp.plugin!r} from {spec.distribution or spec.entry_point})"
            ) from None
    full = pipeline.model_copy(deep=True)
    for name in COMPONENTS:
        model = models[name]
        if model is not None:
            getattr(full, name).params = model.model_dump(mode="json")
    return ResolvedConfig(full, models, source)


def load_config(
    path: "str | Path | dict[str, Any] | PipelineConfig | None" = None,
    overrides: Optional[list[str] | dict[str, Any]] = None,
    registry=None,
) -> ResolvedConfig:
    """Load a pipeline TOML (or a resolved ``config.json`` from a run directory, a raw dict with the TOML's
    structure, or a :class:`PipelineConfig`), apply overrides, resolve."""
    raw: dict[str, Any] = {}
    source = "<defaults>"
    if isinstance(path, PipelineConfig):
        path = path.model_dump(mode="json")
    if isinstance(path, dict):  # a raw config dict, as a TOML file would give
        raw, source, path = dict(path), "<dict>", None
    if path is not None:
        source = str(path)
        if str(path).endswith(".json"):
            try:
                raw = json.loads(read_config_text(path))
            except json.JSONDecodeError as exc:
                raise ConfigError(f"{path}: cannot read JSON config: {exc}") from exc
        else:
            raw = read_toml(path)
        if "variant" in raw:
            raise ConfigError(f"{path}: this is an ablation file ([[variant]] tables); use load_ablation()")
    ov = _normalise_overrides(overrides)
    if ov:
        raw = apply_overrides(raw, ov)
        source += " (with --set " + ", ".join(f"{k}={v!r}" for k, v in ov.items()) + ")"
    return resolve(validate_pipeline(raw, source), registry, source)


def _normalise_overrides(overrides) -> dict[str, Any]:
    if not overrides:
        return {}
    if isinstance(overrides, dict):
        return dict(overrides)
    return dict(parse_override(o) for o in overrides)


# ---------------------------------------------------------------------------------------------- ablation ----
@dataclass
class Variant:
    name: str
    deltas: dict[str, Any]
    config: ResolvedConfig


def is_ablation_file(path: str | Path) -> bool:
    return str(path).endswith(".toml") and "variant" in read_toml(path)


def load_ablation(path: str | Path, overrides=None, registry=None) -> list[Variant]:
    """An ablation file: a base pipeline plus ``[[variant]]`` tables of one-level dotted deltas.

    ``[[variant]]`` tables hold ``name = "..."`` and quoted dotted keys, e.g. ``"loop.plugin" = "none"``.
    ``overrides`` (``--set``) apply to the base before each variant's deltas.
    """
    raw = read_toml(path)
    variants_raw = raw.pop("variant", None)
    if not isinstance(variants_raw, list) or not variants_raw:
        raise ConfigError(f"{path}: an ablation file needs at least one [[variant]] table")
    base = apply_overrides(raw, _normalise_overrides(overrides))
    out: list[Variant] = []
    names: set[str] = set()
    for n, var in enumerate(variants_raw):
        if not isinstance(var, dict):
            raise ConfigError(f"{path}: variant {n} must be a table")
        name = str(var.get("name", f"variant{n}"))
        try:
            from .rundir import check_name

            check_name(name, what="variant name")  # each variant writes into <ablation dir>/<name>/
        except ValueError as exc:
            raise ConfigError(f"{path}: [[variant]] {n}: {exc}") from None
        if name in names:
            raise ConfigError(f"{path}: duplicate variant name {name!r}")
        names.add(name)
        deltas = {k: v for k, v in var.items() if k != "name"}
        for k, v in deltas.items():
            if isinstance(v, dict):
                raise ConfigError(
                    f"{path}: variant {name!r}: key {k!r} is a table; write one-level dotted keys "
                    f'such as "{k}.{next(iter(v), "key")}" = ...'
                )
        source = f"{path} [variant {name!r}]"
        cfg = resolve(validate_pipeline(apply_overrides(base, deltas), source), registry, source)
        out.append(Variant(name, deltas, cfg))
    return out
