"""The typed interfaces every pvslam plugin implements.

The pipeline (:mod:`pvslam_core.pipeline`) drives Algorithm 1 of the PV-SLAM paper against these classes only;
it never imports a plugin.  Plugins register a *factory* ``factory(config_model_instance, context) -> object``
for one of these interfaces (see :mod:`pvslam_core.registry`).  Conventions for poses, images and tensors are
in :mod:`pvslam_core.types`.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterator, Optional, Sequence

import torch

from .types import (
    Category,
    DepthPrior,
    DistancePrior,
    EdgeObservations,
    Frame,
    LoopCandidate,
    LoopClosure,
    OptimizerReport,
    PanopticSegmentation,
    SequenceInfo,
    TrackResult,
)

if TYPE_CHECKING:  # pragma: no cover
    from .slam.graph import FrameGraph


@dataclass
class BuildContext:
    """What a factory may need besides its own config: the compute device, where the run writes, the
    bundle-adjustment resolution (image size / ``ba_downsample``) at which frontends return targets, and the
    sequence the run will process (plugins are built after the dataset reader, so ``info`` is set for every
    plugin but the reader itself)."""

    device: torch.device
    run_dir: Optional[str] = None
    seed: int = 0
    ba_downsample: int = 8
    info: Optional[SequenceInfo] = None


class DatasetReader(ABC):
    """A sequence of frames with timestamps and intrinsics (and optional ground truth)."""

    @abstractmethod
    def info(self) -> SequenceInfo:
        """Sequence facts (frame count, intrinsics of the frames as yielded, what ground truth exists)."""

    @abstractmethod
    def __iter__(self) -> Iterator[Frame]:
        """Frames in time order with ``Frame.index`` counting from 0."""

    def __len__(self) -> int:
        n = self.info().num_frames
        if n is None:  # a camera, a growing folder: len() of a live source is undefined
            raise TypeError(f"{self.info().name}: the number of frames is not known until the source ends")
        return n


class Segmenter(ABC):
    """Image -> panoptic segmentation (the paper's initial PanopticFPN stage)."""

    @abstractmethod
    def segment(self, frame: Frame) -> PanopticSegmentation:
        ...

    def categories(self) -> Optional[Sequence[Category]]:
        """The categories this segmenter labels with (e.g. COCO's 133), or None when it uses the dataset's
        (``SequenceInfo.categories``).  Outputs (panoptic PNG metadata, the panoptic point cloud) use these."""
        return None


class GraphListener:
    """Hears of structural changes of the frame graph, by stable keyframe id (see :mod:`pvslam_core.types`).

    Every stateful component that keys state by keyframe or edge (frontends, loop detectors, the mapper's own
    stores) is told through these two calls, and only through them; nobody else shifts indices.
    """

    def on_keyframe_removed(self, kf_id: int) -> None:
        """Keyframe ``kf_id`` is being removed.  Called *before* the graph forgets it (its pose, depth and index
        are still readable); drop every state about it, including its edges (no separate
        :meth:`on_edges_retired` is sent for edges that touch it)."""

    def on_edges_retired(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        """Edges ``src_ids[e] -> dst_ids[e]`` (int64 ``[E]`` stable ids) left the active graph; drop per-edge state
        (hidden states, correlation volumes, cached targets).  Their last observations stay with the graph for
        the final BA; the frontend will not be asked to observe them again unless they are re-added."""


class Frontend(GraphListener, ABC):
    """Owns per-keyframe features and turns frame-graph edges into flow targets and confidences.

    Call order, for each input frame::

        r = frontend.track(frame, seg)                 # motion filter; r.is_keyframe decides
        if r.is_keyframe:
            frontend.add_keyframe(kf_id, frame, seg)   # kf_id = graph.ids[-1], the new keyframe's stable id
        frontend.prefetch(next_frame)                  # when the next frame is at hand (default: nothing)
        if r.is_keyframe:
            for _ in range(frontend.rounds):           # learned: update -> BA -> update; classical: once
                obs = frontend.observe(graph, ii, jj)
                optimizer.step(graph, obs)

    When :meth:`observe` is called (``ii``/``jj`` are graph *indices*, ``graph.ids[ii]`` their stable ids):

    1. each of the ``rounds`` window rounds after a new keyframe: the active edges that touch the window;
    2. the loop BA after an accepted loop closure: the new loop edges plus the window's active edges;
    3. map initialisation: a pair ``(first keyframe, newer keyframe)`` that need not be a graph edge; when it is
       not one, :meth:`on_edges_retired` follows for it once the mapper is done with it;
    4. the final optimisation: every active edge (retired edges are served from their stored observations).

    A classical flow method answers once per edge (targets cached per edge); a learned RAFT-style operator keeps
    per-edge hidden state and refines its targets against the graph's current reprojection on every call.  Per-edge
    state is dropped on :meth:`~GraphListener.on_edges_retired` and :meth:`~GraphListener.on_keyframe_removed`.
    """

    #: observe -> BA rounds per new keyframe (the config key ``rounds`` of the built-in frontends)
    rounds: int = 1

    @abstractmethod
    def track(self, frame: Frame, seg: Optional[PanopticSegmentation]) -> TrackResult:
        """Motion filter against the last keyframe. Must not change the keyframe set."""

    @abstractmethod
    def add_keyframe(self, kf_id: int, frame: Frame, seg: Optional[PanopticSegmentation]) -> None:
        """Store features of a new keyframe with stable id ``kf_id`` (the graph's newest keyframe)."""

    @abstractmethod
    def observe(self, graph: "FrameGraph", ii: torch.Tensor, jj: torch.Tensor) -> EdgeObservations:
        """Targets and weights for edges ``ii[e] -> jj[e]`` (graph indices) given the graph's current poses and
        depths.  See the class docstring for when it is called."""

    def prefetch(self, frame: Frame) -> None:
        """The next input frame, while this one's keyframe work (edges, BA) is still to come: a frontend may start
        what its next :meth:`track` needs from that frame and the keyframes alone, on another thread.  What
        :meth:`track` returns must not depend on it.  Default: nothing."""

    def discard_pairs(self, src_ids: torch.Tensor, dst_ids: torch.Tensor) -> None:
        """Forget what observing pairs ``src_ids[e] -> dst_ids[e]`` (stable ids) computed and cached, without them
        leaving the graph: the mapper looked at them before the map existed (the initialisation's chain check),
        with no poses to start a flow from; the next :meth:`observe` computes them afresh.  Default: nothing."""

    def initial_depth(self, graph: "FrameGraph", kf_id: int) -> Optional[torch.Tensor]:
        """An inverse-depth guess ``[h, w]`` for new keyframe ``kf_id`` (not yet in ``graph``), or None for the
        mapper's default (the previous keyframe's depth moved into the new pose)."""
        return None

    def depth_prior(self, graph: "FrameGraph", idx: torch.Tensor) -> Optional[DepthPrior]:
        """A prior on the inverse depth of graph keyframes ``idx`` (int64 ``[m]``; ``DepthPrior.ids`` = ``idx``),
        weight 0 where there is none (DROID-SLAM's sensor depth; the flow frontend's road), or None.  The mapper
        asks for the depth sources of every BA call (``EdgeObservations.disp_prior``)."""
        return None

    def distance_prior(self, graph: "FrameGraph", idx: torch.Tensor) -> Optional[DistancePrior]:
        """A prior on the distance between the camera centres of pairs of graph keyframes among ``idx`` (int64
        ``[m]``), or None (the flow frontend's road motion).  The mapper asks for the keyframes of every BA call's
        edges (``EdgeObservations.dist_prior``)."""
        return None


class LoopDetector(GraphListener, ABC):
    """Keyframe -> global descriptor; proposes loop candidates ``(i, j, score)`` with temporal exclusion.

    The detector proposes; the mapper's loop policy (:mod:`pvslam_core.slam.loops`) decides which candidates close a
    loop (verification status, consecutive hits, suppression near recent closures, orientation check)."""

    @abstractmethod
    def add_keyframe(self, kf_id: int, frame: Frame) -> None:
        """Describe and store keyframe ``kf_id`` (called for every keyframe, in order)."""

    @abstractmethod
    def query(self, kf_id: int, skip: Optional[Callable[[int], bool]] = None) -> list[LoopCandidate]:
        """Loop candidates for stored keyframe ``kf_id`` among older keyframes, best first (``i`` = ``kf_id``).
        ``skip(j)`` True means the policy would refuse ``j`` anyway: a detector may leave such candidates out
        before expensive work (geometric verification).  ``verified`` is None when the detector does not verify."""


class Optimizer(ABC):
    """Updates keyframe poses and inverse depths from the graph's targets and weights."""

    @abstractmethod
    def step(self, graph: "FrameGraph", obs: EdgeObservations) -> OptimizerReport:
        """Called after each ``observe`` while a new keyframe is being added (online/local BA)."""

    @abstractmethod
    def loop(self, graph: "FrameGraph", obs: EdgeObservations, loops: list[LoopClosure]) -> OptimizerReport:
        """Relaxed loop BA after loop edges were added (``obs`` covers the loop edges and the local window;
        ``graph.indices_of`` maps the closures' keyframe ids to graph indices)."""

    def finalize(
        self, graph: "FrameGraph", observe: Callable[[torch.Tensor, torch.Tensor], EdgeObservations]
    ) -> OptimizerReport:
        """End of the sequence (offline global BA).  ``observe(ii, jj)`` gives observations of any edges: active
        ones from the frontend, retired ones from the graph's store (``graph.all_edges()`` lists both)."""
        return OptimizerReport(message="no final optimisation")


@dataclass
class VPSState:
    """What a VPS head carries from one frame to the next."""

    frame_index: int
    panoptic: PanopticSegmentation  # temporally consistent ids of that frame
    image: Optional[torch.Tensor] = None  # uint8 [3, H, W]


@dataclass
class MotionCue:
    """Geometry from the VO for warping the previous frame into the current one (all optional).

    ``flow`` and ``depth_prev`` share one resolution ``(h, w)`` (the VO's, usually the BA resolution, coarser than
    the image); ``intrinsics`` belong to that resolution.  A head resizes them to the image it works on."""

    flow: Optional[torch.Tensor] = None  # float32 [2, h, w]: previous-frame pixel -> offset into the current frame
    flow_valid: Optional[torch.Tensor] = None  # bool [h, w]: where ``flow`` was measured (else interpolated)
    depth_prev: Optional[torch.Tensor] = None  # float32 [h, w] z-depth of the previous frame, 0 = unknown
    pose_prev: Optional[torch.Tensor] = None  # float64 [7] T_wc
    pose_cur: Optional[torch.Tensor] = None  # float64 [7] T_wc
    intrinsics: Optional[torch.Tensor] = None  # float [4] fx fy cx cy at the resolution of flow / depth_prev


class VPSHead(ABC):
    """Previous state + current segmentation + flow/depth/pose -> temporally consistent panoptic ids."""

    @abstractmethod
    def update(
        self, prev: Optional[VPSState], frame: Frame, seg: PanopticSegmentation, cue: MotionCue
    ) -> VPSState:
        ...
