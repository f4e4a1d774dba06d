"""The typed interfaces every pvslam plugin implements.

The pipeline (:mod:`pvslam_core.pipeline`) drives Algorithm 1 of the PV-SLAM paper against these classes only;
it never imports a plugin.  Plugins register a *factory* ``factory(config_model_instance, context) -> object``
for one of these interfaces (see :mod:`pvslam_core.registry`).  Conventions for poses, images and tensors are
in :mod:`pvslam_core.types`.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterator, Optional

import torch

from .types import (
    EdgeObservations,
    Frame,
    LoopCandidate,
    OptimizerReport,
    PanopticSegmentation,
    SequenceInfo,
    TrackResult,
)

if TYPE_CHECKING:  # pragma: no cover
    from .slam.graph import FrameGraph


@dataclass
class BuildContext:
    """What a factory may need besides its own config: the compute device, where the run writes, and the
    bundle-adjustment resolution (image size / ``ba_downsample``) at which frontends return targets."""

    device: torch.device
    run_dir: Optional[str] = None
    seed: int = 0
    ba_downsample: int = 8


class DatasetReader(ABC):
    """A sequence of frames with timestamps and intrinsics (and optional ground truth)."""

    @abstractmethod
    def info(self) -> SequenceInfo:
        """Sequence facts (frame count, intrinsics of the frames as yielded, what ground truth exists)."""

    @abstractmethod
    def __iter__(self) -> Iterator[Frame]:
        """Frames in time order with ``Frame.index`` counting from 0."""

    def __len__(self) -> int:
        return self.info().num_frames


class Segmenter(ABC):
    """Image -> panoptic segmentation (the paper's initial PanopticFPN stage)."""

    @abstractmethod
    def segment(self, frame: Frame) -> PanopticSegmentation:
        ...


class Frontend(ABC):
    """Owns per-keyframe features and turns frame-graph edges into flow targets and confidences.

    Call order, for each input frame::

        r = frontend.track(frame, seg)            # motion filter; r.is_keyframe decides
        if r.is_keyframe:
            frontend.add_keyframe(k, frame, seg)  # k = index of the new keyframe in the graph
            for _ in range(frontend.iterations):  # learned: update -> BA -> update; classical: once
                obs = frontend.observe(graph, ii, jj)
                optimizer.step(graph, obs)

    A classical flow method answers once per edge (``iterations == 1``; targets cached per edge); a learned
    RAFT-style operator keeps per-edge hidden state and refines its targets against the graph's current
    reprojection on every call.
    """

    #: number of observe -> BA rounds per new keyframe
    iterations: int = 1

    @abstractmethod
    def track(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> TrackResult:
        """Motion filter against the last keyframe. Must not change the keyframe set."""

    @abstractmethod
    def add_keyframe(self, k: int, frame: Frame, seg: Optional[PanopticSegmentation]) -> None:
        """Store features of a new keyframe with graph index ``k`` (always the next index)."""

    @abstractmethod
    def remove_keyframe(self, k: int) -> None:
        """Forget keyframe ``k``; keyframes after it shift down by one (as in the graph)."""

    @abstractmethod
    def observe(self, graph: "FrameGraph", ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """Targets and weights for edges ``ii[e] -> jj[e]`` given the graph's current poses and depths."""

    def forget_edges(self, ii: torch.Tensor, jj: torch.Tensor) -> None:
        """Edges left the graph; drop any per-edge state kept for them."""

    def initial_depth(self, k: int) -> Optional[torch.Tensor]:
        """An inverse-depth guess for new keyframe ``k`` at the BA resolution, or None for the default."""
        return None


class LoopDetector(ABC):
    """Keyframe -> global descriptor; proposes loop candidates ``(i, j, score)`` with temporal exclusion."""

    @abstractmethod
    def add_keyframe(self, k: int, frame: Frame) -> list[LoopCandidate]:
        """Describe keyframe ``k`` and return verified loop candidates with older keyframes, best first."""

    def remove_keyframe(self, k: int) -> None:
        """Keyframe ``k`` was removed; indices after it shift down by one."""


class Optimizer(ABC):
    """Updates keyframe poses and inverse depths from the graph's targets and weights."""

    @abstractmethod
    def step(self, graph: "FrameGraph", obs: EdgeObservations) -> OptimizerReport:
        """Called after each ``observe`` while a new keyframe is being added (online/local BA)."""

    @abstractmethod
    def loop(self, graph: "FrameGraph", obs: EdgeObservations, loops: list[LoopCandidate]) -> OptimizerReport:
        """Relaxed loop BA after loop edges were added (``obs`` covers the loop edges and the local window)."""

    def finalize(
        self, graph: "FrameGraph", observe: Callable[[torch.Tensor, torch.Tensor], EdgeObservations]
    ) -> OptimizerReport:
        """End of the sequence (offline global BA). ``observe(ii, jj)`` asks the frontend for any edges."""
        return OptimizerReport(message="no final optimisation")


@dataclass
class VPSState:
    """What a VPS head carries from one frame to the next."""

    frame_index: int
    panoptic: PanopticSegmentation  # temporally consistent ids of that frame
    image: Optional[torch.Tensor] = None  # uint8 [3, H, W]


@dataclass
class MotionCue:
    """Geometry from the VO for warping the previous frame into the current one (all optional)."""

    flow: Optional[torch.Tensor] = None  # float32 [2, H, W]: previous-frame pixel -> offset into the current frame
    depth_prev: Optional[torch.Tensor] = None  # float32 [H, W] z-depth of the previous frame
    pose_prev: Optional[torch.Tensor] = None  # float64 [7] T_wc
    pose_cur: Optional[torch.Tensor] = None  # float64 [7] T_wc
    intrinsics: Optional[torch.Tensor] = None  # float [4] fx fy cx cy at full resolution


class VPSHead(ABC):
    """Previous state + current segmentation + flow/depth/pose -> temporally consistent panoptic ids."""

    @abstractmethod
    def update(
        self, prev: Optional[VPSState], frame: Frame, seg: PanopticSegmentation, cue: MotionCue
    ) -> VPSState:
        ...
