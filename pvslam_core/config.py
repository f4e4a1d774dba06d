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
from .slam.config import GraphSection, LoopClosureSection  # noqa: F401 - the SLAM path's sections, next to their code

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
    graph: GraphSection = Field(default_factory=GraphSection, description="the frame graph: BA resolution, map "
                                "initialisation, keyframe and edge policy")
    loop_closure: LoopClosureSection = Field(default_factory=LoopClosureSection,
                                             description="which loop candidates close a loop")
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
    # a (key, value) pair is taken as it is: a value from the command line (a path, a name) is never TOML text
    return dict(o if isinstance(o, tuple) else parse_override(o) for o in overrides)


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
            from .rundir import check_variant_name

            check_variant_name(name)  # each variant writes into <ablation dir>/<name>/
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
