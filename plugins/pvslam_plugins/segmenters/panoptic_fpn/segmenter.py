"""The ``panoptic_fpn`` segmenter plugin: configuration, weights resolution, and segmentation on demand.

**Which frames are segmented.**  The pipeline calls :meth:`Segmenter.segment` on every frame, before the mapper
knows whether the frame becomes a keyframe.  With ``frames = "on_demand"`` (default) the segmenter returns a
:class:`DeferredPanoptic`: a :class:`~pvslam_core.types.PanopticSegmentation` whose network pass runs the first
time its ids, segments or features are read.  The flow frontend and the mapper read them for keyframes only; a VPS
head reads them on every frame.  So keyframes are segmented unless a VPS head (or any other reader) needs every
frame, without the segmenter having to know the rest of the pipeline.  ``frames = "all"`` segments eagerly.
(The network time is then counted in the pipeline's ``map``/``vps`` stage, not ``segment``; :attr:`stats` keeps
the segmenter's own count and seconds.)

**Dynamic masking.**  Every output segment carries ``movable`` (:class:`~pvslam_core.types.Segment`): True for thing
segments whose category is in the movable list (``movable`` in the config, else the category set's own list:
COCO's people/vehicles/animals, VKITTI2's Car/Van/Truck, the synthetic set's car/truck).  The frontend's segment
vote uses movable things only.

**Empty frames.**  A frame where nothing is found gives ids all 0 and no segments; the frontend, the VPS head and
the outputs then behave as with ``segmenter = "none"`` for that frame.
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Literal, Optional

import torch
from pydantic import Field

from pvslam_core.config_base import PluginConfig
from pvslam_core.interfaces import Segmenter
from pvslam_core.types import Category, Frame, PanopticSegmentation

from .config import PresetName

__all__ = ["PanopticFPNSegmenterConfig", "PanopticFPNSegmenter", "DeferredPanoptic", "make_segmenter",
           "build_model", "SHIPPED_WEIGHTS", "DEFAULT_WEIGHTS"]

#: the reduced configuration trained here on the synthetic scenarios (``pvslam train segmenter``), shipped in the package
SHIPPED_WEIGHTS = Path(__file__).with_name("weights") / "reduced_synthetic.pth"
#: sha256 of the shipped file: other bytes (a truncated copy, a Git LFS pointer) are refused, never loaded
SHIPPED_SHA256 = "6e0e80ec13e4236c3f7038596a4c33c7a9d59293db002cf0967ca77768da3cee"
#: default ``weights`` per preset: the shipped file, or a catalogue name (``pvslam weights list``)
DEFAULT_WEIGHTS = {"reduced": str(SHIPPED_WEIGHTS), "coco_r50": "panoptic-fpn-r50-3x-coco",
                   "vkitti2_r50": "pvo-panfpn-vkitti2"}


class PanopticFPNSegmenterConfig(PluginConfig):
    preset: PresetName = Field(
        "reduced", description="architecture: 'reduced' (trained here on the synthetic scenarios, shipped), "
        "'coco_r50' (detectron2 model zoo, 133 COCO categories) or 'vkitti2_r50' (PVO's Virtual KITTI 2 model)")
    weights: Optional[str] = Field(
        None, description="catalogue name or file path (.pkl detectron2, .pth PVO/torch, or a pvslam PanopticFPN "
        "file, which carries its own config); default: the preset's (the shipped checkpoint for 'reduced')")
    device: str = Field("", description="torch device; '' = the run's device")
    frames: Literal["on_demand", "all"] = Field(
        "on_demand", description="on_demand: segment a frame when its segmentation is read (keyframes; every "
        "frame when a VPS head is on); all: segment every frame")
    movable: Optional[list[str]] = Field(
        None, description="category names that count as movable for dynamic masking (thing categories); "
        "default: the category set's list")
    score_thresh: Optional[float] = Field(None, ge=0, le=1, description="box score threshold (default: preset's)")
    instances_confidence_thresh: Optional[float] = Field(
        None, ge=0, le=1, description="panoptic combine: instances below this score are dropped (default: preset's)")
    overlap_thresh: Optional[float] = Field(None, ge=0, le=1, description="panoptic combine overlap threshold")
    stuff_area_limit: Optional[int] = Field(None, ge=0, description="panoptic combine: smallest stuff segment (px)")
    min_size_test: Optional[int] = Field(
        None, ge=0, description="test resize of the shorter side (0 = native size; default: preset's)")
    features: bool = Field(True, description="attach the FPN features p2..p6 to each segmentation (for a VPS head)")


class DeferredPanoptic(PanopticSegmentation):
    """A :class:`PanopticSegmentation` computed on first access, in two stages: reading ``features`` runs only
    the backbone + FPN; reading ``ids`` or ``segments`` also runs the heads and the panoptic combine (on the
    pyramid already computed, if any).  A feature-level VPS head (e.g. ``fusion``) decodes its own fused pyramid
    on most frames, so the segmenter's own decode (most of a reduced-model call) runs only where something
    reads the segmentation itself (keyframes for dynamic masking, the outputs)."""

    def __init__(self, extract: Callable[[], Any], decode: Callable[[Any], PanopticSegmentation],
                 with_features: bool = True) -> None:  # noqa: D107 - no dataclass init
        self._extract: Optional[Callable[[], Any]] = extract
        self._decode = decode
        self._with_features = with_features
        self._pyramid = None  # PyramidBatch of this frame, until decoded
        self._value: Optional[PanopticSegmentation] = None

    @property
    def computed(self) -> bool:
        """Whether the segmentation itself (ids, segments) has been computed."""
        return self._value is not None

    def _pyramid_now(self):
        if self._pyramid is None:
            self._pyramid = self._extract()
            self._extract = None  # drop the frame reference
        return self._pyramid

    def resolve(self) -> PanopticSegmentation:
        if self._value is None:
            self._value = self._decode(self._pyramid_now())
            self._pyramid = None
        return self._value

    @property
    def features(self):
        if self._value is not None:
            return self._value.features
        return self._pyramid_now().to_core(0) if self._with_features else None

    @features.setter
    def features(self, value) -> None:
        self.resolve().features = value

    def _field(name: str):  # noqa: N805 - property factory used in the class body
        return property(lambda self: getattr(self.resolve(), name),
                        lambda self, value: setattr(self.resolve(), name, value))

    ids = _field("ids")
    segments = _field("segments")
    del _field

    def __repr__(self) -> str:
        state = "computed" if self.computed else ("features only" if self._pyramid is not None else "pending")
        return f"DeferredPanoptic({state})"


def build_model(cfg: PanopticFPNSegmenterConfig, progress: bool = False):
    """The configured :class:`~.model.PanopticFPN` with its weights loaded (strictly) and thresholds applied."""
    from pvslam_core.weights import check_shipped, resolve_weights

    from .checkpoint import CheckpointError, load_checkpoint, load_weights, read_weights
    from .config import preset
    from .model import PanopticFPN

    spec = cfg.weights if cfg.weights is not None else DEFAULT_WEIGHTS[cfg.preset]
    if cfg.weights is None and cfg.preset == "reduced":
        path = SHIPPED_WEIGHTS
    else:
        path = resolve_weights(spec, progress=progress)
    if path.resolve() == SHIPPED_WEIGHTS.resolve():
        check_shipped(SHIPPED_WEIGHTS, SHIPPED_SHA256, "segmenter panoptic_fpn", "reinstall pvslam (the file is "
                      "package data of pvslam_plugins.segmenters.panoptic_fpn) or train one (`pvslam train segmenter "
                      "--plugin panoptic_fpn`) and set segmenter.weights", error=CheckpointError)
    if read_weights(path).kind == "pvslam":
        model = load_checkpoint(path)
        want = preset(cfg.preset)
        if (model.cfg.resnet, model.cfg.fpn) != (want.resnet, want.fpn):
            raise ValueError(
                f"segmenter panoptic_fpn: weights {path} hold a ResNet-{model.cfg.resnet.depth} / FPN-"
                f"{model.cfg.fpn.out_channels} network, not the '{cfg.preset}' preset's ResNet-{want.resnet.depth} "
                f"/ FPN-{want.fpn.out_channels}; set segmenter.preset to match the file")
    else:
        model = PanopticFPN(preset(cfg.preset))
        load_weights(model, path, strict=True)
    m = model.cfg
    if cfg.score_thresh is not None:
        m.box_head.score_thresh_test = cfg.score_thresh
    if cfg.instances_confidence_thresh is not None:
        m.combine.instances_confidence_thresh = cfg.instances_confidence_thresh
    if cfg.overlap_thresh is not None:
        m.combine.overlap_thresh = cfg.overlap_thresh
    if cfg.stuff_area_limit is not None:
        m.combine.stuff_area_limit = cfg.stuff_area_limit
    if cfg.min_size_test is not None:
        m.input.min_size_test = cfg.min_size_test
    if cfg.movable is not None:
        things = {c.name.lower() for c in model.categories.things}
        stuff = [n for n in cfg.movable if n.lower() not in things]
        if stuff and all(n.lower() in {c.name.lower() for c in model.categories.categories} for n in stuff):
            raise ValueError(f"segmenter panoptic_fpn: movable {stuff} are stuff categories of "
                             f"{model.categories.name!r}; only thing categories can move "
                             f"(things: {', '.join(c.name for c in model.categories.things)})")
        try:
            model.categories = model.categories.with_movable(cfg.movable)
        except ValueError as exc:
            raise ValueError(f"segmenter panoptic_fpn: movable: {exc}") from None
    return model.eval()


class PanopticFPNSegmenter(Segmenter):
    def __init__(self, config: PanopticFPNSegmenterConfig, device: torch.device | str = "cpu", model=None) -> None:
        self.config = config
        self.device = torch.device(config.device or device)
        self.model = (model if model is not None else build_model(config)).to(self.device).eval()
        self._movable = frozenset(self.model.categories.movable)
        self.stats = {"frames_segmented": 0, "seconds": 0.0, "empty_frames": 0}

    def categories(self) -> list[Category]:
        return list(self.model.categories.categories)

    def segment(self, frame: Frame) -> PanopticSegmentation:
        if self.config.frames == "all":
            return self.segment_now(frame)
        return DeferredPanoptic(lambda: self._extract(frame), self._decode, self.config.features)

    def segment_now(self, frame: Frame) -> PanopticSegmentation:
        """Run the network on ``frame`` now."""
        return self._decode(self._extract(frame))

    @torch.no_grad()
    def _extract(self, frame: Frame):
        """Backbone + FPN -> the frame's PyramidBatch."""
        t0 = time.perf_counter()
        pyramid = self.model.extract([frame.image.to(self.device)])
        self.stats["seconds"] += time.perf_counter() - t0
        return pyramid

    @torch.no_grad()
    def _decode(self, pyramid) -> PanopticSegmentation:
        """Heads + panoptic combine on the frame's own pyramid -> the core's segmentation."""
        t0 = time.perf_counter()
        pan = self.model.decode(pyramid)[0].to_panoptic(with_features=self.config.features)
        segments = [replace(s, movable=bool(s.isthing and s.category_id in self._movable)) for s in pan.segments]
        self.stats["frames_segmented"] += 1
        self.stats["empty_frames"] += int(not segments)
        self.stats["seconds"] += time.perf_counter() - t0
        return PanopticSegmentation(pan.ids.to("cpu", torch.int64), segments, pan.features)


def make_segmenter(config: PanopticFPNSegmenterConfig, context: Any = None) -> PanopticFPNSegmenter:
    device = getattr(context, "device", None) or "cpu"
    return PanopticFPNSegmenter(config, device)
