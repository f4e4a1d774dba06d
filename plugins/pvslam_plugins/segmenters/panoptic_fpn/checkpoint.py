"""Loading PanopticFPN weights safely: detectron2 ``.pkl``, PyTorch ``.pth`` and pvslam's own format.

* ``.pkl`` (detectron2 model zoo, reference/checkpoints.md §2.2): a pickled ``{"model": {name: ndarray},
  "__author__": ..., "matching_heuristics": ...}``.  Unpickling can run arbitrary code, so it goes through
  :class:`RestrictedUnpickler`: only builtin containers/scalars and numpy arrays can be built; any other global
  (``os.system``, ``builtins.eval``, a torch class...) is refused with :class:`UnsafeCheckpoint` naming it.
* ``.pth`` (PVO's panFPN.pth, fvcore checkpoints): ``torch.load(weights_only=True)``; the dict under ``"model"``
  or the whole object; a leading ``module.`` is stripped.
* pvslam's own file (:func:`save_checkpoint`): ``{"format": FORMAT, "config", "categories", "state_dict"}``,
  also read with ``weights_only=True``.

Matching is strict: every model tensor must be present with its shape, and every file tensor must belong to the
model, except the keys detectron2 itself tolerates (``*anchor_generator.cell_anchors.*`` of 2019 files,
``pixel_mean``/``pixel_std``, BN ``num_batches_tracked``), keys owned by another module (PVO's ``fusion_conv1.*``,
returned in :attr:`LoadReport.extra` for the VPS head), and FrozenBN running statistics missing from a ``.pkl``
(filled with 0 / 1 as detectron2 does for files without version metadata).
"""
from __future__ import annotations

import io
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np
import torch
from torch import nn

from .categories import CategorySet
from .config import PanopticFPNConfig
from .layers import FrozenBatchNorm2d

__all__ = [
    "FORMAT",
    "CheckpointError",
    "UnsafeCheckpoint",
    "CheckpointMismatch",
    "RestrictedUnpickler",
    "LoadReport",
    "read_weights",
    "match_state_dict",
    "load_weights",
    "save_checkpoint",
    "load_checkpoint",
]

FORMAT = "pvslam.panoptic_fpn/1"

#: keys detectron2 drops on load: anchors stored as buffers by 2019 files
IGNORED_KEYS = re.compile(r"(^|\.)anchor_generator\.cell_anchors\.\d+$|(^|\.)num_batches_tracked$")
#: keys that belong to another module (PVO's VPS fusion layer); returned, not loaded
EXTRA_KEYS = re.compile(r"^fusion_conv1\.")
NORMALISER_KEYS = ("pixel_mean", "pixel_std")


class CheckpointError(ValueError):
    """A weights file cannot be used (format, content or mismatch)."""


class UnsafeCheckpoint(CheckpointError):
    """A pickle asked for a global outside the allow-list."""


class CheckpointMismatch(CheckpointError):
    """Keys or shapes of a file and the model disagree; ``report`` lists them."""

    def __init__(self, message: str, report: "LoadReport") -> None:
        super().__init__(message)
        self.report = report


# --------------------------------------------------------------------------------------------- restricted pickle
def _numpy_globals() -> dict[tuple[str, str], Any]:
    try:  # pickles name either module path, whatever numpy wrote them
        from numpy._core import multiarray  # numpy >= 2
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core import multiarray

    allowed: dict[tuple[str, str], Any] = {}
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed[(mod, "_reconstruct")] = multiarray._reconstruct
        # a numeric scalar rebuilt from (dtype, raw bytes): no code runs
        allowed[(mod, "scalar")] = multiarray.scalar
    allowed[("numpy", "ndarray")] = np.ndarray
    allowed[("numpy", "dtype")] = np.dtype
    # protocol-2 pickles written by Python 3 store bytes as _codecs.encode(str, "latin1"): str -> bytes only
    import _codecs

    allowed[("_codecs", "encode")] = _codecs.encode
    return allowed


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that builds only dicts, lists, tuples, sets, str/bytes, numbers, bools, None and numpy arrays.

    Builtin containers and scalars need no global in a pickle; numpy arrays need exactly the few constructors
    in :func:`_numpy_globals`.  Anything else, including everything reachable through ``copyreg`` extension
    codes, ends in :meth:`find_class` and is refused.  Persistent ids (torch's storage references) are refused."""

    def __init__(self, file: io.BufferedIOBase, source: str = "<pickle>") -> None:
        super().__init__(file, encoding="latin1")  # detectron2 reads .pkl with latin1 (Python 2 era files)
        self.source = source
        self._allowed = _numpy_globals()

    def find_class(self, module: str, name: str) -> Any:
        try:
            return self._allowed[(module, name)]
        except KeyError:
            raise UnsafeCheckpoint(
                f"{self.source}: refusing to unpickle global '{module}.{name}': a weights .pkl may only contain "
                "dicts, lists, tuples, strings, numbers, bools, None and numpy arrays (this file could run code "
                "when loaded; if you trust it, convert it to a .pth state_dict elsewhere)") from None

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafeCheckpoint(f"{self.source}: refusing a pickle with persistent ids ({str(pid)[:60]!r})")


def _load_pkl(path: Path) -> Any:
    from pvslam_core.weights import refuse_lfs_pointer

    refuse_lfs_pointer(path, "panoptic_fpn weights", error=CheckpointError)
    with open(path, "rb") as f:
        try:
            return RestrictedUnpickler(f, str(path)).load()
        except UnsafeCheckpoint:
            raise
        except Exception as e:  # truncated / corrupt
            raise CheckpointError(f"{path}: not a readable pickle ({type(e).__name__}: {e})") from e


def _load_torch(path: Path) -> Any:
    from pvslam_core.weights import load_torch_file

    return load_torch_file(path, "panoptic_fpn weights", error=CheckpointError, refused=UnsafeCheckpoint)


# --------------------------------------------------------------------------------------------------- reading
@dataclass
class WeightsFile:
    """The tensors of a file, normalised to ``{name: float tensor}``, and what the file said about itself."""

    path: str
    kind: str  # "detectron2-pkl" | "torch" | "pvslam"
    state_dict: dict[str, torch.Tensor]
    config: Optional[dict] = None  # pvslam files only
    categories: Optional[dict] = None  # pvslam files only
    author: str = ""


def _to_tensor(name: str, value: Any, path: Path) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "fiub":
            raise CheckpointError(f"{path}: '{name}' is a numpy array of dtype {value.dtype}; weights must be numeric")
        return torch.from_numpy(np.ascontiguousarray(value))
    raise CheckpointError(f"{path}: '{name}' is a {type(value).__name__}, expected an array/tensor")


def read_weights(path: str | Path) -> WeightsFile:
    """Read a ``.pkl`` (restricted unpickler) or a torch file (``weights_only``) into a :class:`WeightsFile`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: file not found")
    if path.suffix == ".pkl":
        data = _load_pkl(path)
        if not isinstance(data, dict):
            raise CheckpointError(f"{path}: expected a pickled dict, got {type(data).__name__}")
        if "blobs" in data or ("model" in data and "__author__" not in data):
            raise CheckpointError(
                f"{path}: a Caffe2/Detectron1 pickle (no '__author__'); its names need detectron2's heuristic "
                "c2 renaming, which is only used for ImageNet backbone inits, not PanopticFPN checkpoints")
        if data.get("matching_heuristics"):
            raise CheckpointError(
                f"{path}: 'matching_heuristics' is set (author {data.get('__author__')!r}): a converted backbone "
                "init whose names must be matched heuristically, not a PanopticFPN checkpoint")
        if "model" not in data:
            raise CheckpointError(f"{path}: no 'model' entry (keys: {sorted(map(str, data))[:10]})")
        model = data["model"]
        kind, author, cfg, cats = "detectron2-pkl", str(data.get("__author__", "")), None, None
    else:
        data = _load_torch(path)
        if isinstance(data, dict) and "format" in data:
            if data["format"] != FORMAT:
                raise CheckpointError(f"{path}: format {data['format']!r} is not supported (this version reads "
                                      f"{FORMAT!r})")
            model, kind, author = data["state_dict"], "pvslam", "pvslam"
            cfg, cats = data.get("config"), data.get("categories")
        elif isinstance(data, dict):
            model = data.get("model", data)  # fvcore wraps the state_dict in "model"
            kind, author, cfg, cats = "torch", "", None, None
        else:
            raise CheckpointError(f"{path}: expected a dict, got {type(data).__name__}")
    if not isinstance(model, Mapping):
        raise CheckpointError(f"{path}: the model entry is a {type(model).__name__}, expected a dict of arrays")
    sd = {}
    for k, v in model.items():
        name = k[len("module."):] if k.startswith("module.") else k
        sd[name] = _to_tensor(name, v, path)
    return WeightsFile(str(path), kind, sd, cfg, cats, author)


# -------------------------------------------------------------------------------------------------- matching
@dataclass
class LoadReport:
    """What a load matched; empty ``missing``/``unexpected``/``wrong_shape`` = strict success."""

    missing: list[str] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    wrong_shape: list[tuple[str, tuple[int, ...], tuple[int, ...]]] = field(default_factory=list)  # key, file, model
    filled: list[str] = field(default_factory=list)  # FrozenBN stats missing from a .pkl, set to 0 / 1
    ignored: list[str] = field(default_factory=list)  # tolerated keys dropped (cell anchors, num_batches_tracked)
    extra: dict[str, torch.Tensor] = field(default_factory=dict)  # keys for another module (fusion_conv1.*)
    loaded: int = 0

    @property
    def ok(self) -> bool:
        return not (self.missing or self.unexpected or self.wrong_shape)

    def format(self, limit: int = 20) -> str:
        def block(title: str, items: list[str]) -> list[str]:
            if not items:
                return []
            more = [f"    ... and {len(items) - limit} more"] if len(items) > limit else []
            return [f"  {title} ({len(items)}):"] + [f"    {x}" for x in items[:limit]] + more

        lines = [f"  loaded {self.loaded} tensors"]
        lines += block("missing in the file", self.missing)
        lines += block("unexpected in the file", self.unexpected)
        lines += block("wrong shape (file vs model)",
                       [f"{k}: {list(a)} vs {list(b)}" for k, a, b in self.wrong_shape])
        lines += block("filled (FrozenBN stats absent, set to mean 0 / var 1)", self.filled)
        lines += block("ignored (tolerated by detectron2)", self.ignored)
        lines += block("kept for another module", sorted(self.extra))
        return "\n".join(lines)


def _frozen_bn_stats(model: nn.Module) -> set[str]:
    out = set()
    for name, m in model.named_modules():
        if isinstance(m, FrozenBatchNorm2d):
            out.update({f"{name}.running_mean", f"{name}.running_var"})
    return out


def match_state_dict(model: nn.Module, sd: Mapping[str, torch.Tensor], fill_frozen_bn: bool = False
                     ) -> tuple[dict[str, torch.Tensor], LoadReport]:
    """Compare ``sd`` with ``model.state_dict()``: returns the tensors to load (cast to the model's dtype) and the
    report.  Normaliser keys (``pixel_mean``/``pixel_std``) in the file are matched against the model's buffers."""
    target = model.state_dict()
    report = LoadReport()
    out: dict[str, torch.Tensor] = {}
    for k, v in sd.items():
        if k in NORMALISER_KEYS and hasattr(model, k):
            want = getattr(model, k)
            if v.numel() != want.numel():
                report.wrong_shape.append((k, tuple(v.shape), tuple(want.shape)))
            else:
                out[k] = v.reshape(want.shape).to(want.dtype)
            continue
        if EXTRA_KEYS.search(k):
            report.extra[k] = v
            continue
        if k not in target:
            (report.ignored if IGNORED_KEYS.search(k) else report.unexpected).append(k)
            continue
        if tuple(v.shape) != tuple(target[k].shape):
            report.wrong_shape.append((k, tuple(v.shape), tuple(target[k].shape)))
            continue
        out[k] = v.to(target[k].dtype)
    frozen = _frozen_bn_stats(model) if fill_frozen_bn else set()
    for k, t in target.items():
        if k in out:
            continue
        if k in frozen:
            out[k] = torch.zeros_like(t) if k.endswith("running_mean") else torch.ones_like(t)
            report.filled.append(k)
        elif not any(k == w[0] for w in report.wrong_shape):
            report.missing.append(k)
    report.loaded = sum(1 for k in out if k not in report.filled)
    return out, report


def load_weights(model: nn.Module, path: str | Path, strict: bool = True) -> LoadReport:
    """Read ``path`` and load it into ``model``; with ``strict`` any missing/unexpected/mis-shaped key raises
    :class:`CheckpointMismatch` whose message lists them.  Returns the :class:`LoadReport`."""
    wf = read_weights(path)
    tensors, report = match_state_dict(model, wf.state_dict, fill_frozen_bn=wf.kind == "detectron2-pkl")
    if strict and not report.ok:
        raise CheckpointMismatch(f"{path}: the weights do not match the model ({type(model).__name__}):\n"
                                 + report.format(), report)
    normaliser = {k: tensors.pop(k) for k in NORMALISER_KEYS if k in tensors}
    with torch.no_grad():
        model.load_state_dict(tensors, strict=False)
        for k, v in normaliser.items():
            getattr(model, k).copy_(v)
    return report


# ----------------------------------------------------------------------------------------------- own format
def save_checkpoint(model: nn.Module, path: str | Path, extra: Optional[dict] = None,
                    dtype: Optional[torch.dtype] = None) -> None:
    """Write pvslam's PanopticFPN file: format marker, config, categories and the state_dict (torch.save).
    ``dtype`` (e.g. ``torch.float16``) stores the floating-point tensors in that type (half the size); loading
    casts them back to the model's dtype."""
    cfg: PanopticFPNConfig = model.cfg  # type: ignore[assignment]
    cats: CategorySet = model.categories  # type: ignore[assignment]
    sd = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    if dtype is not None:
        sd = {k: v.to(dtype) if v.is_floating_point() else v for k, v in sd.items()}
    payload = {"format": FORMAT, "config": cfg.model_dump(mode="json"), "categories": cats.to_dict(),
               "state_dict": sd}
    if extra:
        payload["extra"] = extra
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu"):
    """Build a :class:`~.model.PanopticFPN` from a pvslam checkpoint (config + categories inside) and load it."""
    from .model import PanopticFPN

    wf = read_weights(path)
    if wf.kind != "pvslam" or wf.config is None or wf.categories is None:
        raise CheckpointError(f"{path}: not a pvslam PanopticFPN checkpoint (format {FORMAT!r}); detectron2/PVO "
                              "files need a config: build PanopticFPN(preset(...)) and call load_weights")
    model = PanopticFPN(PanopticFPNConfig.model_validate(wf.config), CategorySet.from_dict(wf.categories))
    tensors, report = match_state_dict(model, wf.state_dict)
    if not report.ok:
        raise CheckpointMismatch(f"{path}: state_dict does not match its own config:\n" + report.format(), report)
    model.load_state_dict(tensors, strict=True)
    return model.to(device)
