"""Loading and saving DeiT weights: the official ``.pth`` files and this project's own checkpoint format.

Official files (``deit_base_patch16_224-b5f2ef4d.pth``, ``deit_base_distilled_patch16_224-df68dfff.pth``) are a
``torch.save``'d dict whose ``model`` entry is the state_dict; a bare state_dict (timm's hub re-exports) or a
``state_dict`` entry is accepted too.  They are read with ``torch.load(weights_only=True)`` (no code runs) and
loaded strictly: any missing, unexpected or wrongly shaped key raises :class:`CheckpointError` with a report.
The variant (plain / distilled) is detected from ``dist_token``; the architecture is read from the shapes,
except the number of heads, which no shape shows (DeiT uses 64-dimensional heads: 768 / 64 = 12).

Project format (``format == "pvslam.deit"``, ``format_version`` 1), all plain types so that
``weights_only=True`` reads it::

    {"format": "pvslam.deit", "format_version": 1,
     "variant": "plain" | "distilled",
     "config": ViTConfig.to_dict()  (img_size, patch_size, embed_dim, depth, num_heads, mlp_ratio, qkv_bias,
                                     num_classes, distilled, layernorm_eps, drop_path_rate, pos_embed_antialias),
     "state_dict": {name: tensor},
     "pca": PCAWhitening.state_dict() or None,
     "descriptor": {free settings the weights were trained with, e.g. token, input size} or {},
     "meta": {free str/int/float/bool information}}
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Union

import torch
from torch import nn

from .pca import PCAWhitening
from .vit import PRESETS, ViTConfig, VisionTransformer, build_vit

FORMAT = "pvslam.deit"
FORMAT_VERSION = 1

PathLike = Union[str, Path]


class CheckpointError(ValueError):
    """A checkpoint does not fit the model; ``report`` lists every problem."""

    def __init__(self, message: str, report: Optional["KeyReport"] = None) -> None:
        super().__init__(message)
        self.report = report


@dataclass
class KeyReport:
    """Result of comparing a state_dict with a model's expected keys and shapes."""

    missing: list[tuple[str, tuple[int, ...]]] = field(default_factory=list)  # (key, expected shape)
    unexpected: list[tuple[str, tuple[int, ...]]] = field(default_factory=list)  # (key, shape in the file)
    wrong_shape: list[tuple[str, tuple[int, ...], tuple[int, ...]]] = field(default_factory=list)  # (key, exp, got)
    num_expected: int = 0
    num_given: int = 0

    @property
    def ok(self) -> bool:
        return not (self.missing or self.unexpected or self.wrong_shape)

    def __str__(self) -> str:
        if self.ok:
            return f"all {self.num_expected} keys match"
        lines = [f"state_dict does not match the model: {self.num_given} keys given, {self.num_expected} expected"]
        if self.missing:
            lines.append(f"  missing ({len(self.missing)}):")
            lines += [f"    {k}  expected {list(s)}" for k, s in self.missing]
        if self.unexpected:
            lines.append(f"  unexpected ({len(self.unexpected)}):")
            lines += [f"    {k}  {list(s)}" for k, s in self.unexpected]
        if self.wrong_shape:
            lines.append(f"  wrong shape ({len(self.wrong_shape)}):")
            lines += [f"    {k}  expected {list(e)}, got {list(g)}" for k, e, g in self.wrong_shape]
        return "\n".join(lines)


def compare_state_dict(model: nn.Module, state_dict: dict[str, torch.Tensor]) -> KeyReport:
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    given = {k: tuple(v.shape) for k, v in state_dict.items()}
    rep = KeyReport(num_expected=len(expected), num_given=len(given))
    rep.missing = [(k, s) for k, s in expected.items() if k not in given]
    rep.unexpected = [(k, s) for k, s in given.items() if k not in expected]
    rep.wrong_shape = [(k, s, given[k]) for k, s in expected.items() if k in given and given[k] != s]
    return rep


def load_state_dict_strict(model: nn.Module, state_dict: dict[str, torch.Tensor], source: str = "state_dict") -> None:
    """``model.load_state_dict(strict=True)`` preceded by a full key/shape report (raised as CheckpointError)."""
    rep = compare_state_dict(model, state_dict)
    if not rep.ok:
        raise CheckpointError(f"{source}: {rep}", rep)
    model.load_state_dict(state_dict, strict=True)


# --------------------------------------------------------------------------------------------------------------
# official checkpoints
# --------------------------------------------------------------------------------------------------------------
def extract_state_dict(obj: Any, source: str = "checkpoint") -> dict[str, torch.Tensor]:
    """The state_dict inside an official container: ``obj['model']``, else ``obj['state_dict']``, else ``obj``.

    A leading ``module.`` (DistributedDataParallel) is stripped when every key has it.
    """
    if not isinstance(obj, dict):
        raise CheckpointError(f"{source}: expected a dict, got {type(obj).__name__}")
    sd = obj.get("model", obj)
    if isinstance(sd, dict):
        sd = sd.get("state_dict", sd)
    if not isinstance(sd, dict) or not sd:
        raise CheckpointError(f"{source}: no state_dict found (keys: {sorted(obj)[:10]})")
    bad = [k for k, v in sd.items() if not isinstance(v, torch.Tensor)]
    if bad:
        raise CheckpointError(f"{source}: entries that are not tensors: {bad[:5]} (is this a training checkpoint? "
                              "only its 'model' entry is read)")
    if all(k.startswith("module.") for k in sd):
        sd = {k[len("module."):]: v for k, v in sd.items()}
    return sd


def detect_variant(state_dict: dict[str, torch.Tensor]) -> str:
    """``"distilled"`` when the state_dict holds ``dist_token``, else ``"plain"``."""
    return "distilled" if "dist_token" in state_dict else "plain"


def infer_config(state_dict: dict[str, torch.Tensor], num_heads: Optional[int] = None,
                 source: str = "state_dict", **overrides) -> ViTConfig:
    """The :class:`ViTConfig` the shapes imply.  ``num_heads`` defaults to ``embed_dim // 64`` (DeiT's heads)."""
    for k in ("cls_token", "pos_embed", "patch_embed.proj.weight"):
        if k not in state_dict:
            raise CheckpointError(f"{source}: key {k!r} is missing; not a (DeiT) ViT state_dict "
                                  f"(first keys: {list(state_dict)[:5]})")
    distilled = detect_variant(state_dict) == "distilled"
    w = state_dict["patch_embed.proj.weight"]  # [D, 3, p, p]
    D, p = int(w.shape[0]), int(w.shape[-1])
    n_grid = int(state_dict["pos_embed"].shape[1]) - (2 if distilled else 1)
    side = math.isqrt(n_grid)
    if side * side != n_grid:
        raise CheckpointError(f"{source}: pos_embed has {n_grid} grid tokens, not a square grid")
    depth = 1 + max((int(m.group(1)) for k in state_dict if (m := re.match(r"blocks\.(\d+)\.", k))), default=-1)
    if depth == 0:
        raise CheckpointError(f"{source}: no 'blocks.<i>.' keys")
    fc1 = state_dict.get("blocks.0.mlp.fc1.weight")
    mlp_ratio = float(fc1.shape[0]) / D if fc1 is not None else 4.0
    head = state_dict.get("head.weight")
    cfg = dict(img_size=(side * p, side * p), patch_size=p, embed_dim=D, depth=depth,
               num_heads=int(num_heads or max(1, D // 64)), mlp_ratio=mlp_ratio,
               qkv_bias="blocks.0.attn.qkv.bias" in state_dict,
               num_classes=int(head.shape[0]) if head is not None else 0, distilled=distilled)
    cfg.update(overrides)
    return ViTConfig(**cfg)


def load_official(path_or_obj: Union[PathLike, dict], num_heads: Optional[int] = None,
                  expect_variant: Optional[str] = None, **overrides) -> VisionTransformer:
    """Model built from an official DeiT checkpoint (file or loaded dict), loaded strictly, in eval mode.

    ``expect_variant`` (``"plain"`` / ``"distilled"``) turns a variant mismatch into an error; ``overrides`` set
    ViTConfig fields that no shape shows (``pos_embed_antialias``, ``drop_path_rate``).
    """
    source = str(path_or_obj) if not isinstance(path_or_obj, dict) else "checkpoint"
    obj = _torch_load(path_or_obj) if not isinstance(path_or_obj, dict) else path_or_obj
    sd = extract_state_dict(obj, source)
    variant = detect_variant(sd)
    if expect_variant is not None and variant != expect_variant:
        raise CheckpointError(f"{source}: expected a {expect_variant} DeiT, the state_dict is {variant} "
                              f"({'has' if variant == 'distilled' else 'has no'} dist_token)")
    model = build_vit(infer_config(sd, num_heads, source, **overrides), empty=True)
    load_state_dict_strict(model, sd, source)
    return model.eval()


def load_preset_weights(name: str, path_or_obj: Union[PathLike, dict], **overrides) -> VisionTransformer:
    """A named preset (``deit_base_patch16_224`` ...) loaded strictly from an official file: the file must have
    exactly the preset's keys and shapes (152 / 155)."""
    if name not in PRESETS:
        raise KeyError(f"unknown DeiT preset {name!r}; known: {sorted(PRESETS)}")
    source = str(path_or_obj) if not isinstance(path_or_obj, dict) else name
    obj = _torch_load(path_or_obj) if not isinstance(path_or_obj, dict) else path_or_obj
    model = build_vit(ViTConfig(**{**PRESETS[name].to_dict(), **overrides}), empty=True)
    load_state_dict_strict(model, extract_state_dict(obj, source), source)
    return model.eval()


# --------------------------------------------------------------------------------------------------------------
# project format
# --------------------------------------------------------------------------------------------------------------
@dataclass
class LoadedCheckpoint:
    model: VisionTransformer  # eval mode
    pca: Optional[PCAWhitening]
    descriptor: dict  # settings stored with the weights (empty for official files)
    meta: dict
    source_format: str  # "pvslam.deit" or "official"


def save_checkpoint(path: PathLike, model: VisionTransformer, pca: Optional[PCAWhitening] = None,
                    descriptor: Optional[dict] = None, meta: Optional[dict] = None) -> None:
    """Write the project format (see the module docstring); tensors are stored contiguous, detached, on CPU."""
    obj = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "variant": model.config.variant,
        "config": model.config.to_dict(),
        "state_dict": {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
        "pca": pca.state_dict() if pca is not None else None,
        "descriptor": dict(descriptor or {}),
        "meta": dict(meta or {}),
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    torch.save(obj, str(path))


def load_checkpoint(path_or_obj: Union[PathLike, dict], num_heads: Optional[int] = None) -> LoadedCheckpoint:
    """Either format, auto-detected by the ``format`` marker; strict in both cases."""
    source = str(path_or_obj) if not isinstance(path_or_obj, dict) else "checkpoint"
    obj = _torch_load(path_or_obj) if not isinstance(path_or_obj, dict) else path_or_obj
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        if isinstance(obj, dict) and "format" in obj and isinstance(obj["format"], str):
            raise CheckpointError(f"{source}: unknown checkpoint format {obj['format']!r} (expected {FORMAT!r} or "
                                  "an official DeiT file)")
        return LoadedCheckpoint(load_official(obj, num_heads), None, {}, {}, "official")
    version = obj.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(f"{source}: {FORMAT} format_version {version!r}; this code reads {FORMAT_VERSION}")
    missing = [k for k in ("variant", "config", "state_dict") if k not in obj]
    if missing:
        raise CheckpointError(f"{source}: {FORMAT} checkpoint lacks {missing}")
    try:
        cfg = ViTConfig(**obj["config"])
    except TypeError as exc:
        raise CheckpointError(f"{source}: bad config {obj['config']}: {exc}") from exc
    if cfg.variant != obj["variant"]:
        raise CheckpointError(f"{source}: variant {obj['variant']!r} but config.distilled={cfg.distilled}")
    model = build_vit(cfg, empty=True)
    load_state_dict_strict(model, obj["state_dict"], source)
    pca = PCAWhitening.from_state_dict(obj["pca"]) if obj.get("pca") is not None else None
    return LoadedCheckpoint(model.eval(), pca, dict(obj.get("descriptor") or {}), dict(obj.get("meta") or {}),
                            FORMAT)


def _torch_load(path: PathLike) -> Any:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"DeiT checkpoint not found: {p}")
    from pvslam_core.weights import load_torch_file

    return load_torch_file(p, "DeiT checkpoint", error=CheckpointError)
