"""The sweep file: sequences (built-in scenarios x seeds, or full dataset sections) x ablation variants.

A sweep file is an ablation file (a base pipeline plus ``[[variant]]`` deltas, see :func:`pvslam_core.config.
load_ablation`) with a ``[sweep]`` table and optional ``[[sequence]]`` tables instead of a ``[dataset]``::

    [sweep]
    name = "table7"                        # the sweep directory is <output_dir>/<name>
    scenarios = ["driving_loop", "indoor_handheld"]    # built-in synthetic scenarios ...
    seeds = [0, 1]                         # ... each generated and run with every seed
    scenario_params = { num_frames = 200 } # extra dataset parameters for the scenario sequences

    [[sequence]]                           # any dataset, as a full dataset section
    name = "kitti_00"
    dataset = { plugin = "kitti", root = "data/kitti", sequence = "00" }
    seeds = [0]                            # run.seed values (default: [sweep] seeds)

    [segmenter]                            # base pipeline tables, shared by every cell
    plugin = "labels"

    [[variant]]
    name = "no_loop"
    "loop.plugin" = "none"

A scenario sequence with seed s uses ``dataset.seed = s`` (a different generated scene) and ``run.seed = s``; a
``[[sequence]]`` seed only sets ``run.seed`` (RANSAC and other random choices).  Every cell is resolved here,
so every config error of the whole grid is reported before anything runs, naming the file and the key path.
"""
from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from pydantic import Field, ValidationError, field_validator

from ..config import (ConfigError, ResolvedConfig, _normalise_overrides, apply_overrides, format_validation_error,
                      read_toml, resolve, validate_pipeline)
from ..config_base import PluginConfig

SWEEP_KEYS = ("sweep", "sequence", "variant")
# Run settings that change how a cell runs, not what it computes: left out of the cell's identity (its key), so
# resuming with another worker count does not invalidate finished cells.
_NON_IDENTITY_RUN_KEYS = ("name", "output_dir", "progress", "threads")


class SweepSection(PluginConfig):
    name: Optional[str] = Field(None, description="sweep name = folder under output_dir (default: the file's stem)")
    output_dir: str = Field("sweeps", description="folder that holds sweep directories")
    scenarios: list[str] = Field(default_factory=list, description="built-in scenarios (`pvslam synth --list`)")
    seeds: list[int] = Field(default_factory=lambda: [0], min_length=1, description="seeds of every sequence")
    scenario_plugin: str = Field("synthetic", description="dataset plugin that generates the scenarios")
    scenario_params: dict[str, Any] = Field(default_factory=dict,
                                            description="extra dataset parameters of the scenario sequences")
    workers: int = Field(0, ge=0, description="runs at a time (0 = one per core of the machine or cluster)")
    threads: int = Field(0, ge=0, description="torch/OpenCV threads per run (0 = cores // workers)")
    plots: bool = Field(True, description="write the ATE bar chart and trajectory overlays")

    @field_validator("seeds")
    @classmethod
    def _unique_seeds(cls, v: list[int]) -> list[int]:
        if len(set(v)) != len(v):
            raise ValueError(f"duplicate seeds in {v}")
        return v


class SequenceSpec(PluginConfig):
    name: str = Field(..., min_length=1, description="sequence name (table rows, cell folder names)")
    dataset: dict[str, Any] = Field(..., description="a full dataset section: {plugin = ..., ...}")
    seeds: Optional[list[int]] = Field(None, min_length=1, description="run.seed values (default: [sweep] seeds)")

    @field_validator("dataset")
    @classmethod
    def _has_plugin(cls, v: dict[str, Any]) -> dict[str, Any]:
        if "plugin" not in v:
            raise ValueError("missing key 'plugin' (the dataset plugin to use)")
        return v


class SweepModel(PluginConfig):
    sweep: SweepSection = Field(..., description="the grid: seeds, variants, where and how to run")
    sequence: list[SequenceSpec] = Field(default_factory=list, description="the sequences ([[sequence]] tables)")


@dataclass
class Cell:
    """One run of the grid: a sequence, a seed and a variant, with its fully resolved config."""

    sequence: str
    seed: int
    variant: str
    name: str  # folder name under <sweep>/cells (sanitised, unique)
    config: ResolvedConfig
    deltas: dict[str, Any]  # everything applied on top of the base (for the run's overrides.json)
    key: str = ""  # hash of the config without the run-only keys: a finished cell is reused only for the same key

    @property
    def meta(self) -> dict[str, Any]:
        return {"sequence": self.sequence, "seed": self.seed, "variant": self.variant, "key": self.key}


@dataclass
class SweepPlan:
    name: str
    source: str
    output_dir: Path
    section: SweepSection
    sequences: list[str]
    variants: list[str]
    cells: list[Cell] = field(default_factory=list)

    @property
    def directory(self) -> Path:
        return self.output_dir / sanitise(self.name)


# ------------------------------------------------------------------------------------------------ names --
_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")


def sanitise(text: str, max_len: int = 60) -> str:
    """A file-name-safe form: letters, digits, ``. _ - +``; no leading dot (so never ``.`` or ``..``)."""
    s = _UNSAFE.sub("_", str(text)).strip("._-")[:max_len].strip("._-")
    return s or "x"


def cell_name(sequence: str, seed: int, variant: str) -> str:
    """``<sequence>__seed<k>__<variant>``; when sanitising changed a part, a short hash of the raw triple keeps
    two different cells from sharing a folder (``a/b`` and ``a_b``)."""
    parts = (sanitise(sequence), f"seed{int(seed)}", sanitise(variant))
    name = "__".join(parts)
    if parts[0] != sequence or parts[2] != variant:
        raw = json.dumps([sequence, int(seed), variant]).encode()
        name += "__" + hashlib.sha1(raw).hexdigest()[:8]
    return name


def config_key(cfg: ResolvedConfig) -> str:
    data = cfg.to_dict()
    data["run"] = {k: v for k, v in data["run"].items() if k not in _NON_IDENTITY_RUN_KEYS}
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------------- load --
def load_sweep(path: str | Path, overrides=None, output_dir: Optional[str | Path] = None,
               registry=None) -> SweepPlan:
    """Read, validate and expand a sweep file into its cells (every cell's config resolved)."""
    src = str(path)
    raw = read_toml(path)
    ov = _normalise_overrides(overrides)
    if bad := [k for k in ov if k.split(".")[0] in ("dataset", "sequence", "variant")]:
        raise ConfigError(f"--set {bad[0]}: a sweep's datasets and variants are its grid; change "
                          "sweep.scenario_params, the [[sequence]] tables or the [[variant]] tables instead")
    sweep_ov = {k: v for k, v in ov.items() if k.startswith("sweep.")}
    if sweep_ov:  # e.g. --set sweep.seeds=[0] for a quick look
        raw = apply_overrides(raw, sweep_ov)
        src += " (with --set " + ", ".join(f"{k}={v!r}" for k, v in sweep_ov.items()) + ")"
    overrides = {k: v for k, v in ov.items() if k not in sweep_ov}
    if "sweep" not in raw:
        raise ConfigError(f"{src}: a sweep file needs a [sweep] table (with scenarios and/or [[sequence]] tables)")
    if "dataset" in raw:
        raise ConfigError(f"{src}: a sweep file takes its datasets from [sweep] scenarios and [[sequence]] tables; "
                          "move the [dataset] table into a [[sequence]] (dataset = {...})")
    try:
        model = SweepModel.model_validate({k: raw[k] for k in ("sweep", "sequence") if k in raw})
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, src, SweepModel)) from None
    sec = model.sweep
    variants_raw = raw.get("variant")
    if not isinstance(variants_raw, list) or not variants_raw:
        raise ConfigError(f"{src}: a sweep file needs at least one [[variant]] table (an empty one = the base)")
    variants = _variants(src, variants_raw)
    sequences = _sequences(src, sec, model.sequence, registry)
    base = apply_overrides({k: v for k, v in raw.items() if k not in SWEEP_KEYS}, _normalise_overrides(overrides))

    plan = SweepPlan(name=sec.name or Path(path).stem, source=src,
                     output_dir=Path(output_dir if output_dir is not None else sec.output_dir), section=sec,
                     sequences=[s.name for s in sequences], variants=[v for v, _ in variants])
    names: dict[str, tuple] = {}
    for seq in sequences:
        for seed in seq.seeds:
            # A scenario's seed also picks the generated scene; a dataset section is used as written.
            dataset = {**seq.dataset, "seed": seed} if seq.scenario else seq.dataset
            for vname, vdeltas in variants:
                deltas = {"dataset": dataset, "run.seed": seed, **vdeltas}
                seq_name = seq.name
                label = f"{src} [sequence {seq_name!r}, seed {seed}, variant {vname!r}]"
                cfg = resolve(validate_pipeline(apply_overrides(base, deltas), label), registry, label)
                name = cell_name(seq_name, seed, vname)
                if name in names:  # only after truncation of two long names; the hash suffix makes it unlikely
                    raise ConfigError(f"{src}: cells {names[name]} and {(seq_name, seed, vname)} map to one "
                                      f"folder {name!r}; shorten the names")
                names[name] = (seq_name, seed, vname)
                plan.cells.append(Cell(seq_name, seed, vname, name, cfg, deltas, config_key(cfg)))
    return plan


def _variants(src: str, variants_raw: list) -> list[tuple[str, dict[str, Any]]]:
    out: list[tuple[str, dict[str, Any]]] = []
    for n, var in enumerate(variants_raw):
        if not isinstance(var, dict):
            raise ConfigError(f"{src}: variant {n} must be a table")
        name = str(var.get("name", f"variant{n}"))
        if name in (v for v, _ in out):
            raise ConfigError(f"{src}: duplicate variant name {name!r}")
        deltas = {k: v for k, v in var.items() if k != "name"}
        for k, v in deltas.items():
            if isinstance(v, dict):
                raise ConfigError(f"{src}: variant {name!r}: key {k!r} is a table; write one-level dotted keys "
                                  f'such as "{k}.{next(iter(v), "key")}" = ...')
            if k == "dataset" or k.startswith("dataset."):
                raise ConfigError(f"{src}: variant {name!r}: key {k!r}: variants cannot change the dataset "
                                  "(the sequences are the other axis of the grid)")
        out.append((name, deltas))
    return out


@dataclass
class _Sequence:
    name: str
    dataset: dict[str, Any]
    seeds: list[int]
    scenario: bool  # a built-in scenario: the seed also goes into dataset.seed


def _sequences(src: str, sec: SweepSection, seqs: list[SequenceSpec], registry=None) -> list[_Sequence]:
    out: list[_Sequence] = []
    quiet: dict[str, Any] = {}
    if sec.scenarios:
        if {"scenario", "seed"} & set(sec.scenario_params):
            raise ConfigError(f"{src}: sweep.scenario_params cannot set 'scenario' or 'seed' (the grid sets them)")
        from ..registry import PluginError, get_registry

        try:
            spec = (registry or get_registry()).get("dataset", sec.scenario_plugin)
        except PluginError as exc:
            raise ConfigError(f"{src}: sweep.scenario_plugin: {exc}") from None
        if "scenarios" in spec.extras and (unknown := [s for s in sec.scenarios if s not in spec.extras["scenarios"]]):
            raise ConfigError(f"{src}: sweep.scenarios: unknown scenario(s) {unknown}; available: "
                              + ", ".join(spec.extras["scenarios"]))
        if "progress" in spec.config_model.model_fields:  # no generator progress bar under the grid's display
            quiet["progress"] = False
    for scen in sec.scenarios:
        dataset = {"plugin": sec.scenario_plugin, **quiet, **sec.scenario_params, "scenario": scen}
        out.append(_Sequence(scen, dataset, list(sec.seeds), True))
    for s in seqs:
        out.append(_Sequence(s.name, dict(s.dataset), list(s.seeds or sec.seeds), False))
    if not out:
        raise ConfigError(f"{src}: no sequences: set sweep.scenarios and/or add [[sequence]] tables")
    seen: set[str] = set()
    for s in out:
        if s.name in seen:
            raise ConfigError(f"{src}: duplicate sequence name {s.name!r}")
        seen.add(s.name)
    return out
