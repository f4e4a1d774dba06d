"""``pvslam train INTERFACE --plugin NAME``: training entry points that plugins register.

A learned plugin registers a :class:`Trainer` with its component (``register(name, factory, Config, trainer=
Trainer(TrainConfig, run))``).  The core only loads the training config (TOML + ``--set``, validated by the
trainer's own pydantic model with the usual error messages), creates the output folder, saves the resolved config
there (``train_config.json``) and calls ``run(config, out_dir, resume)``; what the trainer does (data, losses,
checkpoints, logs) is the plugin's.  Trainers write into ``out_dir`` only and resume from it when asked; a resumed
run starts from the configuration saved there, and what ``--config`` and ``--set`` give replaces single keys of it
(more iterations, say), each change named on the console.

The trainers share one optimisation loop, :class:`TrainingLoop` (resume, CSV logs, schedule, gradient step,
progress bar, validation, checkpoints): each subclasses it with its batches, losses and schedule.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from .config import ConfigError, apply_overrides, format_validation_error, read_toml, _normalise_overrides

NOTICE = logging.getLogger("pvslam.notice")  # choices made for the user; the CLI shows them on the console


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


def _dotted(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A TOML table as dotted-key overrides (``{"a": {"b": 1}}`` -> ``{"a.b": 1}``)."""
    out: dict[str, Any] = {}
    for k, v in table.items():
        # an empty table stays a value, so the trainer's model still rejects an unknown one
        out.update(_dotted(v, f"{prefix}{k}.") if isinstance(v, dict) and v else {f"{prefix}{k}": v})
    return out


def load_train_config(trainer: Trainer, path: Optional[str | Path], overrides=None,
                      base: Optional[tuple[dict[str, Any], str]] = None):
    """The trainer's validated config: its defaults, or ``base`` (``(raw, source)``: a resumed run's saved config),
    with the TOML file ``path`` and the ``--set`` overrides on top."""
    from pydantic import ValidationError

    raw, source = base if base is not None else ({}, "<defaults>")
    if path is not None:
        raw = apply_overrides(raw, _dotted(read_toml(path)))
        source = str(path) if base is None else f"{source} with {path}"
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
    if out_dir is None:
        if resume:
            raise ValueError("--resume needs --out (the folder of the run to continue)")
        out_dir = Path("runs") / f"train-{interface}-{plugin}-{time.strftime('%Y%m%d-%H%M%S')}"
    out = Path(out_dir)
    if resume:
        cfg = _resumed_config(trainer, out, interface, plugin, config, overrides)
    else:
        cfg = load_train_config(trainer, config, overrides)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "train_config.json", {"interface": interface, "plugin": plugin,
                                                  "config": json.loads(cfg.model_dump_json())})
    summary = trainer.run(cfg, out, resume) or {}
    write_json_atomic(out / "summary.json", summary)
    return out, summary


def _resumed_config(trainer: Trainer, out: Path, interface: str, plugin: str, config, overrides):
    """A resumed run's config: the one saved in ``out/train_config.json`` with ``config`` / ``overrides`` on top (a
    resume without them continues exactly the run that was started, not the trainer's defaults)."""
    saved = out / "train_config.json"
    if not out.is_dir():
        raise FileNotFoundError(f"--resume: {out} does not exist")
    if not saved.is_file():
        raise FileNotFoundError(f"--resume: {saved} not found ({out} is not the folder of a training run)")
    data = json.loads(saved.read_text())
    if (data.get("interface"), data.get("plugin")) != (interface, plugin):
        raise ValueError(f"--resume: {out} holds a run of {data.get('interface')} --plugin {data.get('plugin')}, "
                         f"not {interface} --plugin {plugin}")
    before = data.get("config") or {}
    cfg = load_train_config(trainer, config, overrides, base=(before, str(saved)))
    after = json.loads(cfg.model_dump_json())
    for key in sorted(set(before) | set(after)):
        if before.get(key) != after.get(key):
            NOTICE.warning("resuming %s: %s changed from %r to %r", out, key, before.get(key), after.get(key))
    return cfg


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
                        elapsed: float, extra: Optional[dict] = None) -> None:
    """Write a trainer's resumable state atomically (a ``.tmp`` beside ``path``, then a rename, so a run killed
    while saving keeps its previous checkpoint): model, optimiser, the data generator's state, the step counter
    under ``counter_key``, the training seconds so far and the trainer's ``extra`` entries."""
    import torch

    path = Path(path)
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(), "generator": generator.get_state(),
                counter_key: counter, "elapsed": elapsed, **(extra or {})}, tmp)
    tmp.replace(path)


def load_training_state(path: Path, model, optimizer, generator, counter_key: str) -> tuple[int, float, dict]:
    """Restore what :func:`save_training_state` wrote (``weights_only``); returns ``(counter, elapsed, state)``,
    ``state`` holding the trainer's extra entries.  Files of the deit trainer's earlier format (``opt``, ``gen``)
    load too."""
    from .weights import load_torch_file

    what = "--resume: the training state"
    state = load_torch_file(path, what, error=ValueError)
    try:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"] if "optimizer" in state else state["opt"])
        generator.set_state(state["generator"] if "generator" in state else state["gen"])
        return int(state[counter_key]), float(state["elapsed"]), state
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError) as exc:
        lines = str(exc).strip().splitlines() or [""]
        why = f"no entry {exc.args[0]!r}" if isinstance(exc, KeyError) else lines[0]
        raise ValueError(f"{what} {path} does not fit this trainer ({type(exc).__name__}: {why}); start without "
                         "--resume or give another --out") from None


def _keep_rows(path: Path, fields: list[str], counter_key: str, upto: Optional[int]) -> None:
    """Rewrite a CSV log with its header and the rows up to step ``upto`` (None: a fresh log): a resumed run drops
    the rows written after its checkpoint."""
    import csv

    rows = list(csv.DictReader(path.open())) if (upto is not None and path.is_file()) else []
    rows = [r for r in rows if int(r[counter_key]) <= (upto or 0)]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


class TrainingLoop:
    """The optimisation loop the trainers share: resume, logs, learning-rate schedule, gradient step, progress bar,
    validation and checkpoints.  A trainer subclasses it and supplies only what differs:

    * :meth:`stop_reason` (None to go on), :meth:`learning_rate`, :meth:`loss` (the forward pass on the next
      batch: the loss tensor and the step's values) and :meth:`log_row` (the CSV row of a step);
    * optionally :meth:`validate` (a row of the validation log) with :meth:`validation_due` and
      :meth:`final_validation`, :meth:`checkpoint_due`, :meth:`on_checkpoint`, :meth:`extra_state` (entries saved
      with the checkpoint and given back to ``__init__`` through ``self.resumed``) and :meth:`postfix`.

    One step: learning rate, loss, a finite-loss check, ``zero_grad``, ``backward``, gradient-norm clip (when
    ``grad_clip``), ``optimizer.step``; then the counter, the training seconds (the steps' own time), the log row,
    the bar, validation when due and a checkpoint when due.  The logs are flushed before a validation or a
    checkpoint; on resume the rows after the checkpoint are dropped.  Ctrl-C saves the state and re-raises.
    """

    counter: str = "step"  # name of the step counter: CSV column and checkpoint key
    state_file: str = "last.pt"
    log_file: str = "loss.csv"
    log_fields: list[str] = []
    val_file: Optional[str] = None
    val_fields: list[str] = []
    grad_clip: Optional[float] = None
    checkpoint_every: int = 50
    desc: str = "train"
    bar_options: dict = {"dynamic_ncols": True}

    def __init__(self, cfg: Any, out: Path, model, optimizer, generator, resume: bool, total: int) -> None:
        self.cfg, self.out, self.model, self.optimizer, self.generator = cfg, Path(out), model, optimizer, generator
        self.total = total
        self.step, self.elapsed, self.resumed = 0, 0.0, {}
        self.final_val: Optional[dict] = None  # the validation row written after the loop, if any
        state = self.out / self.state_file
        if resume and state.is_file():
            self.step, self.elapsed, self.resumed = load_training_state(state, model, optimizer, generator,
                                                                        self.counter)
        upto = self.step if resume else None
        _keep_rows(self.out / self.log_file, self.log_fields, self.counter, upto)
        if self.val_file:
            _keep_rows(self.out / self.val_file, self.val_fields, self.counter, upto)

    # ------------------------------------------------------------------------------------ trainer's part --
    def stop_reason(self) -> Optional[str]:
        """Why the run stops before the next step (None: go on)."""
        raise NotImplementedError

    def learning_rate(self) -> float:
        raise NotImplementedError

    def loss(self) -> tuple[Any, dict]:
        """The forward pass on the next batch: ``(loss tensor, values of the step)``."""
        raise NotImplementedError

    def log_row(self, values: dict, lr: float) -> dict:
        """The training log's row of the step just taken (``self.step`` and ``self.elapsed`` are updated)."""
        raise NotImplementedError

    def postfix(self, values: dict) -> dict:
        return {}

    def failed_batch(self) -> str:
        """Words that name the batch of a non-finite loss."""
        return ""

    def validate(self) -> Optional[dict]:
        """Validation at ``self.step``; returns the validation log's row (None: nothing to log)."""
        return None

    def validation_due(self) -> bool:
        return False

    def final_validation(self, steps_run: int) -> bool:
        """Validate once more after the loop (when the last step was not validated)."""
        return False

    def checkpoint_due(self) -> bool:
        return self.step % self.checkpoint_every == 0

    def on_checkpoint(self) -> None:
        """After a checkpoint written inside the loop (e.g. refresh a plot)."""

    def extra_state(self) -> dict:
        return {}

    # --------------------------------------------------------------------------------------- the loop --
    def save(self) -> None:
        save_training_state(self.out / self.state_file, self.model, self.optimizer, self.generator, self.counter,
                            self.step, self.elapsed, self.extra_state())

    def run_validation(self) -> Optional[dict]:
        import csv

        row = self.validate()
        if row is not None and self.val_file:
            with (self.out / self.val_file).open("a", newline="") as f:
                csv.DictWriter(f, fieldnames=self.val_fields, extrasaction="ignore").writerow(row)
        return row

    def _take_step(self) -> tuple[dict, float]:
        import torch

        lr = self.learning_rate()
        for g in self.optimizer.param_groups:
            g["lr"] = lr
        loss, values = self.loss()
        if not torch.isfinite(loss):
            raise FloatingPointError(f"{self.counter} {self.step}: non-finite loss{self.failed_batch()}: {values}")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.grad_clip)
        self.optimizer.step()
        return values, lr

    def run(self) -> str:
        """Train until :meth:`stop_reason` says why; returns that reason.  The state is saved at the end."""
        import csv

        from tqdm import tqdm

        start = self.step
        reason = None
        bar = tqdm(**{"total": self.total, "initial": self.step, "desc": self.desc, "disable": not self.cfg.progress,
                      **self.bar_options})
        try:
            with (self.out / self.log_file).open("a", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=self.log_fields, extrasaction="ignore")
                while (reason := self.stop_reason()) is None:
                    t0 = time.perf_counter()
                    values, lr = self._take_step()
                    self.step += 1
                    self.elapsed += time.perf_counter() - t0
                    writer.writerow(self.log_row(values, lr))
                    bar.update(1)
                    bar.set_postfix(self.postfix(values))
                    if self.validation_due():
                        f.flush()
                        self.run_validation()
                    if self.checkpoint_due():
                        f.flush()
                        self.save()
                        self.on_checkpoint()
        except KeyboardInterrupt:
            self.save()
            bar.close()
            raise
        bar.close()
        self.final_val = self.run_validation() if self.final_validation(self.step - start) else None
        self.save()
        return reason
