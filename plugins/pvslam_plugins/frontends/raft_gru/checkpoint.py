"""Loading and saving ``raft_gru`` weights: droid.pth, PVO checkpoints and this project's own format.

Every file is read with ``torch.load(..., weights_only=True)``: a file that needs arbitrary unpickling (code
execution) is refused with :class:`CheckpointError`, never loaded.

Accepted layouts (detected from the content, see :func:`convert`):

* **droid.pth** (DROID-SLAM): a flat state_dict, usually with DDP's ``module.`` prefix.  Converted exactly as
  ``Droid.load_weights``: ``module.`` removed, then ``update.weight.2.*`` and ``update.delta.2.*`` cut to their
  first 2 output rows (the file has more; the count found is reported in :attr:`LoadedCheckpoint.notes`).
* **PVO** (``vkitti2_dy_train_semiv4_080000.pth``): a flat state_dict with ``update.delta_dy.*``,
  ``update.delta_mask.*`` and ``update.agg.upmask_disp.*``; ``module.`` removed, nothing sliced (as PVO's loader).
  ``update.param_linear.*`` / ``update.global_avg_pool.*`` select ``use_aff_bri``.
* **pvslam** (written by :func:`save_checkpoint`)::

      {"format": "pvslam.raft_gru", "format_version": 1,
       "variant": "droid" | "pvo", "use_aff_bri": bool,
       "state_dict": {name: tensor},             # RaftGruNet keys, no prefix, ready for a strict load
       "training": None | {...},                  # optional resumable state (optimizer, step, RNG, ...)
       "meta": {...}}                             # free-form str/int/float/bool/list/dict

A checkpoint that does not fit the model raises :class:`CheckpointError` listing missing keys, unexpected keys
and shape mismatches (name, expected, got), each list truncated to its first entries.
"""
from __future__ import annotations

import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import torch

from pvslam_core.outputs._atomic import atomic_open

from .net import RaftGruNet
from .update import VARIANTS

FORMAT = "pvslam.raft_gru"
FORMAT_VERSION = 1
DROID_SLICED_HEADS = ("update.weight.2.weight", "update.weight.2.bias", "update.delta.2.weight", "update.delta.2.bias")
PVO_MARKERS = ("update.delta_dy.", "update.delta_mask.", "update.agg.upmask_disp.")
AFF_BRI_MARKERS = ("update.param_linear.", "update.global_avg_pool.")
MAX_LISTED = 12  # entries shown per list in error messages

PathLike = Union[str, os.PathLike]


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be read safely or does not fit the network (message names keys and shapes)."""


@dataclass
class LoadedCheckpoint:
    """A checkpoint converted to :class:`RaftGruNet` keys.

    Attributes:
        variant: ``"droid"`` or ``"pvo"``.
        use_aff_bri: PVO's optional photometric-affine head is present.
        state_dict: ``{name: tensor}`` in RaftGruNet naming (``fnet.*``, ``cnet.*``, ``update.*``).
        source: where it came from: ``"droid"`` (droid.pth layout), ``"pvo"`` or ``"pvslam"``.
        origin: file path (or ``"<dict>"``), used in messages.
        training: the pvslam format's optional training state (None otherwise).
        meta: the pvslam format's ``meta`` (empty otherwise).
        notes: what the conversion did (e.g. ``"update.weight.2.weight: kept 2 of 3 rows"``).
    """

    variant: str
    use_aff_bri: bool
    state_dict: dict
    source: str
    origin: str = "<dict>"
    training: Optional[dict] = None
    meta: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)


def _listing(items: list[str], indent: str = "    ") -> str:
    shown = items[:MAX_LISTED]
    more = f"\n{indent}... and {len(items) - len(shown)} more" if len(items) > len(shown) else ""
    return "".join(f"\n{indent}{s}" for s in shown) + more


def read_file(path: PathLike, map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True, map_location=...)`` with readable errors."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    from pvslam_core.weights import refuse_lfs_pointer

    refuse_lfs_pointer(path, "raft_gru checkpoint", error=CheckpointError)
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(
            f"{path}: refused - the file holds objects that torch.load(weights_only=True) will not unpickle "
            f"(loading them could run arbitrary code). Re-save only the state_dict (tensors in plain dicts) on a "
            f"trusted machine.\n  torch says: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
        ) from exc
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({type(exc).__name__}: {exc})") from exc


def detect_variant(keys) -> tuple[str, bool]:
    """``(variant, use_aff_bri)`` from RaftGruNet-style keys (``module.`` already removed)."""
    keys = list(keys)
    if not any(k.startswith("update.") for k in keys):
        raise CheckpointError(
            "not a DROID/PVO network state_dict: no 'update.*' keys; first keys:" + _listing(sorted(keys))
        )
    pvo = any(k.startswith(PVO_MARKERS) for k in keys)
    aff = any(k.startswith(AFF_BRI_MARKERS) for k in keys)
    return ("pvo" if pvo else "droid"), aff


def _as_state_dict(obj: Any, origin: str) -> dict:
    if not isinstance(obj, Mapping) or not obj:
        raise CheckpointError(f"{origin}: expected a state_dict (name -> tensor), got {type(obj).__name__}")
    bad = [f"{k}: {type(v).__name__}" for k, v in obj.items() if not isinstance(v, torch.Tensor)]
    if bad:
        raise CheckpointError(
            f"{origin}: expected a state_dict (name -> tensor) or a '{FORMAT}' checkpoint; these entries are not "
            f"tensors:" + _listing(bad)
        )
    return dict(obj)


def convert(obj: Any, origin: str = "<dict>", variant: Optional[str] = None) -> LoadedCheckpoint:
    """Turn a loaded object (any accepted layout, see module doc) into a :class:`LoadedCheckpoint`.

    ``variant``: the expected variant; a checkpoint of the other variant raises (None: accept either).
    """
    if variant is not None and variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS} or None, got {variant!r}")
    if isinstance(obj, Mapping) and "format" in obj:
        if obj.get("format") != FORMAT:
            raise CheckpointError(f"{origin}: unknown checkpoint format {obj.get('format')!r} (expected {FORMAT!r})")
        version = obj.get("format_version")
        if version != FORMAT_VERSION:
            raise CheckpointError(f"{origin}: {FORMAT} format_version {version!r} is not supported (this code reads "
                                  f"{FORMAT_VERSION})")
        sd = _as_state_dict(obj.get("state_dict"), origin + " ['state_dict']")
        found, aff = detect_variant(sd)
        if obj.get("variant") != found or bool(obj.get("use_aff_bri", False)) != aff:
            raise CheckpointError(
                f"{origin}: header says variant={obj.get('variant')!r}, use_aff_bri={obj.get('use_aff_bri')!r} "
                f"but the keys are those of variant={found!r}, use_aff_bri={aff}"
            )
        ckpt = LoadedCheckpoint(found, aff, sd, "pvslam", origin, obj.get("training"), dict(obj.get("meta") or {}))
    else:
        raw = _as_state_dict(obj, origin)
        sd = {k.replace("module.", ""): v for k, v in raw.items()}  # as upstream: every occurrence
        found, aff = detect_variant(sd)
        ckpt = LoadedCheckpoint(found, aff, sd, found, origin)
        if found == "droid":
            # Droid.load_weights: droid.pth stores more output rows in these heads; the network uses 2.
            for k in DROID_SLICED_HEADS:
                if k in sd and sd[k].dim() > 0 and sd[k].shape[0] > 2:
                    ckpt.notes.append(f"{k}: kept 2 of {sd[k].shape[0]} rows")
                    sd[k] = sd[k][:2]
    if variant is not None and ckpt.variant != variant:
        raise CheckpointError(f"{origin}: holds a {ckpt.variant!r} network, but variant={variant!r} was asked for")
    return ckpt


def load_checkpoint(
    source: Union[PathLike, Mapping], map_location: Any = "cpu", variant: Optional[str] = None
) -> LoadedCheckpoint:
    """Read (``weights_only=True``) and convert a checkpoint file, or convert an already loaded dict."""
    if isinstance(source, Mapping):
        return convert(source, "<dict>", variant)
    return convert(read_file(source, map_location), str(source), variant)


def check_state_dict(model: torch.nn.Module, state_dict: Mapping, origin: str = "<dict>") -> None:
    """Raise :class:`CheckpointError` unless ``state_dict`` has exactly ``model``'s keys and shapes."""
    expected = model.state_dict()
    missing = [k for k in expected if k not in state_dict]
    unexpected = [k for k in state_dict if k not in expected]
    mismatched = [
        f"{k}: expected {tuple(v.shape)}, got {tuple(state_dict[k].shape)}"
        for k, v in expected.items()
        if k in state_dict and tuple(state_dict[k].shape) != tuple(v.shape)
    ]
    if not (missing or unexpected or mismatched):
        return
    desc = getattr(model, "variant", None)
    parts = [f"{origin} does not fit RaftGruNet(variant={desc!r}"
             f"{', use_aff_bri=True' if getattr(model, 'use_aff_bri', False) else ''}):"]
    if missing:
        parts.append(f"  missing keys ({len(missing)}):" + _listing(missing))
    if unexpected:
        parts.append(f"  unexpected keys ({len(unexpected)}):" + _listing(unexpected))
    if mismatched:
        parts.append(f"  shape mismatches ({len(mismatched)}):" + _listing(mismatched))
    raise CheckpointError("\n".join(parts))


def load_model(
    source: Union[PathLike, Mapping], map_location: Any = "cpu", variant: Optional[str] = None
) -> tuple[RaftGruNet, LoadedCheckpoint]:
    """Build the network a checkpoint describes and load it strictly; returns ``(model in eval mode, ckpt)``.

    The model is on ``map_location`` (when it is a device) and float32.
    """
    ckpt = load_checkpoint(source, map_location, variant)
    model = RaftGruNet(ckpt.variant, ckpt.use_aff_bri)
    check_state_dict(model, ckpt.state_dict, ckpt.origin)
    model.load_state_dict(ckpt.state_dict, strict=True)
    if isinstance(map_location, (str, torch.device)):
        model.to(map_location)
    return model.eval(), ckpt


_SAFE_SCALARS = (str, int, float, bool, type(None), torch.Tensor, torch.Size, torch.dtype, torch.device)


def _check_safe(obj: Any, where: str) -> None:
    """Reject objects ``torch.load(weights_only=True)`` would refuse, before writing (names the offending path)."""
    if isinstance(obj, _SAFE_SCALARS):
        return
    if isinstance(obj, Mapping):
        for k, v in obj.items():
            if not isinstance(k, (str, int)):
                raise TypeError(f"{where}: key {k!r} of type {type(k).__name__} is not weights_only-safe")
            _check_safe(v, f"{where}[{k!r}]")
        return
    if isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _check_safe(v, f"{where}[{i}]")
        return
    raise TypeError(f"{where}: {type(obj).__name__} is not weights_only-safe (use tensors, numbers, str, lists, dicts)")


def save_checkpoint(
    path: PathLike,
    model: RaftGruNet,
    training: Optional[Mapping] = None,
    meta: Optional[Mapping] = None,
) -> Path:
    """Write a pvslam checkpoint (layout in the module doc) atomically; it loads back with weights_only=True.

    ``training``: optional resumable state, e.g. ``{"step": int, "optimizer": opt.state_dict(),
    "scheduler": sched.state_dict(), "rng": torch.get_rng_state()}``; ``meta``: free-form description.
    """
    obj = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "variant": model.variant,
        "use_aff_bri": bool(model.use_aff_bri),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "training": None if training is None else dict(training),
        "meta": dict(meta or {}),
    }
    _check_safe(obj, "checkpoint")
    path = Path(path)
    with atomic_open(path, "wb") as f:
        torch.save(obj, f)
    return path
