"""Fitting a resolved config to the data it runs on, before the plugins are built.

The default pipeline segments with the ``labels`` oracle (the dataset's own panoptic ground truth), which suits
the built-in synthetic data and Virtual KITTI 2 but not a user's video.  A segmenter plugin that needs labels says
so with the registration extra ``needs_gt_panoptic=True``; when the data has none (``SequenceInfo.has_gt_panoptic``
False) the segmenter is replaced, instead of failing at frame 0:

* by an installed learned segmenter that declares itself ready -- the extra ``auto_ready``, a zero-argument
  callable that is true when the plugin runs with its default config (e.g. its weights are on disk);
* else by none: segmentation and VPS are off, and so is panoptic evaluation (it needs labels too).

A segmenter the user chose that needs no labels is never touched.

The BA resolution (``graph.ba_downsample``, default 1/8) follows the camera: every threshold the frame graph and
the frontend express in BA pixels (keyframe flow, redundancy, proximity edges, dynamic residuals) was chosen with
the 320x240 synthetic camera at 1/8, whose focal length is 272 / 8 = 34 BA pixels per radian, and a flow in BA
pixels is that focal length times an angle of motion.  Unless the user set ``graph.ba_downsample`` or the frontend
registered a fixed one (the registration extra ``ba_downsample``: a network's feature stride), it is halved while
``min(fx, fy) / ba_downsample`` is below :data:`BA_MIN_FOCAL` (a power-of-two divisor of the old factor, so the
reader's crop stays valid).  The focal length and not the image height: a wide image of few rows is not a coarse
one (docs/decisions.md: BA_MIN_FOCAL).  The motion thresholds among them (keyframe flow, redundancy, proximity edges,
observed parallax) are angles of view in reference BA pixels: :func:`ba_px_scale` turns them into this camera's BA
pixels, so a larger or smaller processing size does not change what they mean (1.0 at the 320x240 default camera).

Each change is one line on the ``pvslam.notice`` logger, which the command line prints on the console (and
log.txt keeps).
"""
from __future__ import annotations

import logging
from typing import Optional

from .config import DISABLED, Component, ResolvedConfig
from .types import Intrinsics, SequenceInfo

NOTICE = logging.getLogger("pvslam.notice")  # choices made for the user; the CLI shows them on the console
# the BA resolution is halved while the focal length at it (BA px per radian) would be below this: about 34 / sqrt(2),
# so that it lands nearest the 34 every BA-pixel threshold was chosen at (docs/decisions.md: BA_MIN_FOCAL)
BA_MIN_FOCAL = 24.0
# the focal length at the BA resolution (BA px per radian) of the camera every BA-pixel motion threshold was chosen
# with: the 320x240 synthetic camera's 272 px at 1/8 (see ba_px_scale)
REF_BA_FOCAL = 34.0


def ba_px_scale(intr: Intrinsics, ba_downsample: int) -> float:
    """This camera's BA pixels per reference BA pixel: a motion threshold (keyframe flow, redundancy, proximity,
    observed parallax) is an angle of view, ``value / REF_BA_FOCAL`` radians, so it means the same at any
    processing size; multiply the threshold by this to get it in this camera's BA pixels."""
    return (min(float(intr.fx), float(intr.fy)) / int(ba_downsample)) / REF_BA_FOCAL


def _ready_segmenters(registry, exclude: str) -> list[str]:
    ready = []
    for name in registry.names("segmenter"):
        spec = registry.get("segmenter", name)
        check = spec.extras.get("auto_ready")
        if name == exclude or spec.extras.get("needs_gt_panoptic") or not callable(check):
            continue
        try:
            if check():
                ready.append(name)
        except Exception as exc:  # noqa: BLE001 - a plugin that cannot tell is not ready
            NOTICE.debug("segmenter %r: auto_ready() raised %s: %s", name, type(exc).__name__, exc)
    return ready


def fit_to_sequence(resolved: ResolvedConfig, info: SequenceInfo, registry) -> tuple[ResolvedConfig, list[str]]:
    """``resolved`` with the components the data cannot feed replaced and the BA resolution fitted to the image
    size (a new object), and one note per change; ``(resolved, [])`` unchanged when nothing needs to change."""
    resolved, notes = _fit_segmenter(resolved, info, registry)
    resolved, more = _fit_ba_resolution(resolved, info, registry)
    return resolved, notes + more


def say_processing_size(info: SequenceInfo) -> None:
    """One console line when the reader processes the frames at another size than the input's."""
    src, out = info.input_intrinsics, info.intrinsics
    if src is not None and (src.width, src.height) != (out.width, out.height):
        NOTICE.warning("processing %dx%d frames at %dx%d", src.width, src.height, out.width, out.height)


def _fit_ba_resolution(resolved: ResolvedConfig, info: SequenceInfo, registry) -> tuple[ResolvedConfig, list[str]]:
    g = resolved.pipeline.graph
    if "ba_downsample" in g.model_fields_set:
        return resolved, []
    fe = resolved.pipeline.frontend
    if fe.enabled and registry.get("frontend", fe.plugin).extras.get("ba_downsample") is not None:
        return resolved, []  # the frontend works at one fixed resolution (a network's feature stride)
    intr = info.intrinsics
    f, ds = min(float(intr.fx), float(intr.fy)), g.ba_downsample
    new = ds
    while new % 2 == 0 and f / new < BA_MIN_FOCAL:
        new //= 2
    if new == ds:
        return resolved, []
    pcfg = resolved.pipeline.model_copy(deep=True)
    pcfg.graph.ba_downsample = new
    note = (f"graph.ba_downsample: {new} (at 1/{ds} the {int(intr.width)}x{int(intr.height)} camera's focal length "
            f"{f:.0f} px is {f / ds:.1f} BA px, below {BA_MIN_FOCAL:g}; set "
            f"graph.ba_downsample to keep 1/{ds})")
    NOTICE.warning(note)
    return ResolvedConfig(pcfg, dict(resolved.models), resolved.source), [note]


def _fit_segmenter(resolved: ResolvedConfig, info: SequenceInfo, registry) -> tuple[ResolvedConfig, list[str]]:
    seg = resolved.pipeline.segmenter
    if not seg.enabled or info.has_gt_panoptic:
        return resolved, []
    if not registry.get("segmenter", seg.plugin).extras.get("needs_gt_panoptic"):
        return resolved, []
    pcfg = resolved.pipeline.model_copy(deep=True)
    models = dict(resolved.models)
    ready = _ready_segmenters(registry, seg.plugin)
    why = f"the '{seg.plugin}' segmenter needs panoptic labels, which {info.name} does not have"
    replacement: Optional[str] = ready[0] if ready else None
    if replacement is not None:
        model = registry.get("segmenter", replacement).config_model()
        pcfg.segmenter = Component(plugin=replacement, params=model.model_dump(mode="json"))
        models["segmenter"] = model
        note = f"segmenter: {replacement} ({why}; {replacement} is installed and ready)"
    else:
        pcfg.segmenter = Component(plugin=DISABLED)
        models["segmenter"] = None
        if pcfg.vps.enabled:  # VPS tracks the segmenter's segments: nothing to track
            pcfg.vps = Component(plugin=DISABLED)
            models["vps"] = None
        note = (f"segmenter: none ({why}): segmentation, video panoptic segmentation and panoptic evaluation are "
                "off; for panoptic output fetch detectron2's COCO model (`pvslam weights fetch "
                "panoptic-fpn-r50-3x-coco`) and set segmenter.plugin = \"panoptic_fpn\", segmenter.preset = "
                "\"coco_r50\"")
    NOTICE.warning(note)
    return ResolvedConfig(pcfg, models, resolved.source), [note]
