"""``pvslam train INTERFACE --plugin NAME``: training entry points that plugins register.

A learned plugin registers a :class:`Trainer` with its component (``register(name, factory, Config, trainer=
Trainer(TrainConfig, run))``).  The core only loads the training config (TOML + ``--set``, validated by the
trainer's own pydantic model with the usual error messages), creates the output folder, saves the resolved config
there (``train_config.json``) and calls ``run(config, out_dir, resume)``; what the trainer does (data, losses,
checkpoints, logs) is the plugin's.  Trainers write into ``out_dir`` only and resume from it when asked.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from .config import ConfigError, apply_overrides, format_validation_error, read_toml, _normalise_overrides


@dataclass(frozen=True)
class Trainer:
    """What a plugin registers as its ``trainer`` extra."""

    config_model: type  # a PluginConfig subclass: the training parameters
    run: Callable[[Any, Path, bool], dict]  # (config, out_dir, resume) -> summary (printed; saved as summary.json)
    description: str = ""


def find_trainer(interface: str, plugin: str, registry=None) -> Trainer:
    from .registry import PluginError, get_registry

    reg = registry or get_registry()
    spec = reg.get(interface, plugin)
    trainer = spec.extras.get("trainer")
    if trainer is None:
        trainable = [f"{i} {n}" for (i, n), s in sorted(reg.plugins.items()) if s.extras.get("trainer") is not None]
        raise PluginError(f"{interface} plugin {plugin!r} has no trainer; trainable plugins: "
                          + (", ".join(trainable) or "none installed"))
    return trainer


def load_train_config(trainer: Trainer, path: Optional[str | Path], overrides=None):
    from pydantic import ValidationError

    raw: dict[str, Any] = read_toml(path) if path is not None else {}
    source = str(path) if path is not None else "<defaults>"
    ov = _normalise_overrides(overrides)
    if ov:
        raw = apply_overrides(raw, ov)
        source += " (with --set " + ", ".join(f"{k}={v!r}" for k, v in ov.items()) + ")"
    try:
        return trainer.config_model.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, trainer.config_model)) from None


def train(interface: str, plugin: str, config: Optional[str | Path] = None, overrides=None,
          out_dir: Optional[str | Path] = None, resume: bool = False, registry=None) -> tuple[Path, dict]:
    """Run a plugin's trainer; returns ``(out_dir, summary)``.  With ``resume`` ``out_dir`` must exist."""
    from .outputs.metrics import write_json_atomic

    trainer = find_trainer(interface, plugin, registry)
    cfg = load_train_config(trainer, config, overrides)
    if out_dir is None:
        if resume:
            raise ValueError("--resume needs --out (the folder of the run to continue)")
        out_dir = Path("runs") / f"train-{interface}-{plugin}-{time.strftime('%Y%m%d-%H%M%S')}"
    out = Path(out_dir)
    if resume and not out.is_dir():
        raise FileNotFoundError(f"--resume: {out} does not exist")
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "train_config.json", {"interface": interface, "plugin": plugin,
                                                  "config": json.loads(cfg.model_dump_json())})
    summary = trainer.run(cfg, out, resume) or {}
    write_json_atomic(out / "summary.json", summary)
    return out, summary


def prepare_run(cfg: Any, out_dir: str | Path) -> tuple[Path, Path]:
    """The common start of a trainer's ``run``: torch intra-op threads (``cfg.threads`` when > 0), the global torch
    seed (``cfg.seed``, when the config has one), and the data cache folder (``cfg.data_cache``, else
    ``out_dir/data``: rendered training data is reused by a resumed run).  Returns ``(out_dir, cache_dir)``."""
    import torch

    threads = int(getattr(cfg, "threads", 0) or 0)
    if threads > 0:
        torch.set_num_threads(threads)
    if getattr(cfg, "seed", None) is not None:
        torch.manual_seed(int(cfg.seed))
    out = Path(out_dir)
    cache = Path(cfg.data_cache) if getattr(cfg, "data_cache", None) else out / "data"
    return out, cache


def save_training_state(path: Path, model, optimizer, generator, counter_key: str, counter: int,
                        elapsed: float) -> None:
    """Write a trainer's resumable state atomically (a ``.tmp`` beside ``path``, then a rename, so a run killed
    while saving keeps its previous checkpoint): model, optimiser, the data generator's state, the step counter
    under ``counter_key`` and the training seconds so far."""
    import torch

    path = Path(path)
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "generator": generator.get_state(),
                counter_key: counter, "elapsed": elapsed}, tmp)
    tmp.replace(path)


def load_training_state(path: Path, model, optimizer, generator, counter_key: str) -> tuple[int, float]:
    """Restore what :func:`save_training_state` wrote (``weights_only``); returns ``(counter, elapsed)``."""
    import torch

    state = torch.load(Path(path), map_location="cpu", weights_only=True)
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    generator.set_state(state["generator"])
    return int(state[counter_key]), float(state["elapsed"])
