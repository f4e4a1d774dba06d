"""The oracle ``labels`` segmenter (see the package docstring)."""
from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from pydantic import Field

from pvslam_core.config_base import PluginConfig
from pvslam_core.interfaces import Segmenter
from pvslam_core.types import Frame, PanopticSegmentation, Segment

#: stride of the panoptic id convention ``category_id * 1000 + instance`` used when instances are merged
ID_STRIDE = 1000


class LabelsSegmenterConfig(PluginConfig):
    drop_instances: bool = Field(
        False,
        description="merge all instances of a thing category into one segment per category (simulates a "
        "semantic-only segmenter); merged segments keep isthing=True",
    )
    score: float = Field(1.0, ge=0.0, le=1.0, description="confidence written into every segment")


class MissingPanopticLabels(ValueError):
    """A frame given to the ``labels`` segmenter has no ``gt_panoptic``."""


class LabelsSegmenter(Segmenter):
    """Returns ``frame.gt_panoptic`` (a copy; resized with nearest neighbour if its size differs from the image)."""

    def __init__(self, config: LabelsSegmenterConfig | None = None) -> None:
        self.config = config or LabelsSegmenterConfig()

    def segment(self, frame: Frame) -> PanopticSegmentation:
        gt = frame.gt_panoptic
        if gt is None:
            label = f"frame {frame.index}" + (f" ({frame.name})" if frame.name else "")
            raise MissingPanopticLabels(
                f"{label} has no panoptic labels: the labels segmenter needs a dataset with panoptic ground truth "
                "(e.g. synthetic or vkitti2); use segmenter.plugin = 'none' (or a learned segmenter) for this dataset"
            )
        ids = gt.ids.detach().cpu().to(torch.int64)
        if tuple(ids.shape) != (frame.height, frame.width):
            ids = F.interpolate(ids[None, None].double(), size=(frame.height, frame.width), mode="nearest")[0, 0]
            ids = ids.round().to(torch.int64)
        else:
            ids = torch.from_numpy(ids.numpy().copy())  # numpy copy: cheaper than torch clone on small CPUs
        score = float(self.config.score)
        segments = [Segment(s.id, s.category_id, s.isthing, score) for s in gt.segments]
        if self.config.drop_instances:
            ids, segments = _merge_instances(ids, segments, score)
        return PanopticSegmentation(ids=ids, segments=segments)


def _merge_instances(
    ids: torch.Tensor, segments: list[Segment], score: float
) -> tuple[torch.Tensor, list[Segment]]:
    """One segment per thing category (id ``category_id * 1000`` unless that id belongs to another segment)."""
    things: dict[int, list[int]] = {}
    for s in segments:
        if s.isthing:
            things.setdefault(s.category_id, []).append(s.id)
    if not things:
        return ids, segments
    kept = [s for s in segments if not s.isthing]
    used = {s.id for s in kept}
    next_free = max([s.id for s in segments] + [0]) + 1
    src: list[int] = []
    dst: list[int] = []
    for cat in sorted(things):
        new_id = cat * ID_STRIDE if cat > 0 else 0
        if new_id <= 0 or new_id in used:
            new_id, next_free = next_free, next_free + 1
        used.add(new_id)
        kept.append(Segment(new_id, cat, True, score))
        for sid in things[cat]:
            src.append(sid)
            dst.append(new_id)
    src_t = torch.tensor(src, dtype=torch.int64)
    dst_t = torch.tensor(dst, dtype=torch.int64)
    order = torch.argsort(src_t)
    src_t, dst_t = src_t[order], dst_t[order]
    flat = ids.reshape(-1)
    pos = torch.searchsorted(src_t, flat).clamp(max=len(src_t) - 1)
    hit = src_t[pos] == flat
    out = torch.where(hit, dst_t[pos], flat).reshape(ids.shape)
    return out, kept


def make_segmenter(config: LabelsSegmenterConfig, context: Any = None) -> LabelsSegmenter:
    return LabelsSegmenter(config)
