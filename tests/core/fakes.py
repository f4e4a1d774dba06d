"""Test-only plugins for the framework tests: a tiny exact scene and a frontend that answers from ground truth.

They are registered directly (``build_registry(extra_modules=(fakes,))``), never shipped as product plugins.
Scene: two fronto-parallel planes (z = 4 on the left half of the view, z = 8 on the right), camera translating
along +x with identity rotation, so flow targets are exact closed-form values.
"""
from __future__ import annotations

import torch
from pydantic import Field

from pvslam_core.config_base import PluginConfig
from pvslam_core.interfaces import DatasetReader, Frontend, LoopDetector, Optimizer, Segmenter, VPSState, VPSHead
from pvslam_core.registry import hookimpl
from pvslam_core.types import (EdgeObservations, Frame, Intrinsics, LoopCandidate, OptimizerReport,
                               PanopticSegmentation, Segment,
                               SequenceInfo, TrackResult)

W, H, F = 64, 48, 40.0
SPEED = 0.05  # metres per frame along +x


def depth_map(h: int, w: int) -> torch.Tensor:
    d = torch.full((h, w), 4.0)
    d[:, w // 2:] = 8.0
    return d


class FakeDatasetConfig(PluginConfig):
    frames: int = Field(12, ge=2, description="number of frames")
    speed: float = Field(SPEED, gt=0, description="metres per frame along +x")
    input_scale: int = Field(1, ge=1, description="say the input was this many times the frames' size (a reader "
                             "that shrank it)")


class FakeDataset(DatasetReader):
    def __init__(self, cfg: FakeDatasetConfig):
        self.n = cfg.frames
        self.speed = cfg.speed
        self.k = Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
        s = cfg.input_scale  # the frames are the input shrunk by s: k == k_input.scaled(1 / s)
        self.k_input = None if s == 1 else Intrinsics(F * s, F * s, (W * s - 1) / 2, (H * s - 1) / 2, W * s, H * s)

    def info(self) -> SequenceInfo:
        return SequenceInfo("fake", self.n, self.k, has_gt_pose=True, has_gt_depth=True,
                            input_intrinsics=self.k_input)

    def __iter__(self):
        g = torch.Generator().manual_seed(0)
        img = torch.randint(0, 255, (3, H, W), generator=g, dtype=torch.uint8)
        for i in range(self.n):
            pose = torch.tensor([self.speed * i, 0, 0, 0, 0, 0, 1], dtype=torch.float64)
            yield Frame(i, 0.1 * i, img.clone(), self.k, gt_pose=pose, gt_depth=depth_map(H, W), name=f"fake{i}")


class FakeSegmenterConfig(PluginConfig):
    pass


class FakeSegmenter(Segmenter):
    def segment(self, frame: Frame) -> PanopticSegmentation:
        ids = torch.full((frame.height, frame.width), 1000, dtype=torch.int64)
        ids[:, frame.width // 2:] = 2001
        return PanopticSegmentation(ids, [Segment(1000, 1, False), Segment(2001, 2, True)])


class ExactFrontendConfig(PluginConfig):
    keyframe_every: int = Field(2, ge=1, description="every n-th frame is a keyframe")
    max_pair_gap: int = Field(0, ge=0, description="edges between keyframes further apart than this get zero "
                              "weight (a flow that breaks on fast motion); 0: no limit")


class ExactFrontend(Frontend):
    """Targets from the known scene: u_j = u_i - f (x_j - x_i) / z at the BA resolution."""

    rounds = 1

    def __init__(self, cfg: ExactFrontendConfig, ds: int):
        self.cfg = cfg
        self.ds = ds
        self.kf_x: dict[int, float] = {}  # stable keyframe id -> camera x
        self.count = 0

    def track(self, frame, seg):
        self.count += 1
        x = float(frame.gt_pose[0])
        is_kf = self.count % self.cfg.keyframe_every == 0
        if not self.kf_x:
            return TrackResult(is_kf, 1.0)
        return TrackResult(is_kf, 1.0, *self._tw(self.kf_x[max(self.kf_x)], x, self.ds))

    def _tw(self, xi: float, xj: float, ds: int):
        h, w = H // ds, W // ds
        f = F / ds
        ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                                indexing="ij")
        z = depth_map(h, w)
        target = torch.stack([xs - f * (xj - xi) / z, ys])
        return target, torch.ones(2, h, w)

    def add_keyframe(self, kf_id, frame, seg):
        self.kf_x[kf_id] = float(frame.gt_pose[0])

    def on_keyframe_removed(self, kf_id):
        del self.kf_x[kf_id]

    def observe(self, graph, ii, jj):
        h, w = graph.ba_shape
        ds = H // h
        ids = graph.ids
        tw = [self._tw(self.kf_x[int(ids[i])], self.kf_x[int(ids[j])], ds) for i, j in zip(ii.tolist(), jj.tolist())]
        gap = self.cfg.max_pair_gap
        tw = [(t, w_ * 0 if gap and abs(i - j) > gap else w_) for (t, w_), i, j in zip(tw, ii.tolist(), jj.tolist())]
        return EdgeObservations(ii, jj, torch.stack([t for t, _ in tw]), torch.stack([w_ for _, w_ in tw]))


class RecordingOptimizerConfig(PluginConfig):
    pass


class RecordingOptimizer(Optimizer):
    """Counts calls; leaves the graph alone (the framework tests do not test BA)."""

    loop_calls = 0  # class-wide: the tests read it after a run

    def __init__(self):
        self.steps = 0

    def step(self, graph, obs):
        self.steps += 1
        return OptimizerReport(iterations=0, num_edges=int(obs.ii.numel()))

    def loop(self, graph, obs, loops):
        RecordingOptimizer.loop_calls += 1
        return OptimizerReport()


class EveryKeyframeLoopConfig(PluginConfig):
    start: int = Field(4, ge=2, description="keyframes from this id on report a verified loop with keyframe id 1")


class EveryKeyframeLoop(LoopDetector):
    """A revisit that never ends: every keyframe from ``start`` on closes a loop with keyframe 1."""

    def __init__(self, cfg: EveryKeyframeLoopConfig):
        self.cfg = cfg

    def add_keyframe(self, kf_id, frame):
        pass

    def query(self, kf_id, skip=None):
        return [LoopCandidate(kf_id, 1, 0.99, verified=True, inliers=100)] if kf_id >= self.cfg.start else []


class PassVPSConfig(PluginConfig):
    pass


class PassVPS(VPSHead):
    def update(self, prev, frame, seg, cue):
        return VPSState(frame.index, seg)


@hookimpl
def register_datasets(register):
    register("fake", lambda c, ctx: FakeDataset(c), FakeDatasetConfig, description="test-only exact scene")


@hookimpl
def register_segmenters(register):
    register("fake_seg", lambda c, ctx: FakeSegmenter(), FakeSegmenterConfig, description="test-only")


@hookimpl
def register_frontends(register):
    register("exact", lambda c, ctx: ExactFrontend(c, ctx.ba_downsample), ExactFrontendConfig, description="test-only")


@hookimpl
def register_optimizers(register):
    register("recording", lambda c, ctx: RecordingOptimizer(), RecordingOptimizerConfig, description="test-only")


@hookimpl
def register_loop_detectors(register):
    register("every_kf", lambda c, ctx: EveryKeyframeLoop(c), EveryKeyframeLoopConfig, description="test-only")


@hookimpl
def register_vps_heads(register):
    register("pass", lambda c, ctx: PassVPS(), PassVPSConfig, description="test-only")


FAKE_PIPELINE = """
[run]
progress = false
output_dir = "{output_dir}"
[dataset]
plugin = "fake"
frames = 12
[segmenter]
plugin = "fake_seg"
[frontend]
plugin = "exact"
[loop]
plugin = "none"
[optimizer]
plugin = "recording"
[vps]
plugin = "pass"
[graph]
ba_downsample = 4
[graph.init]
warmup = 3
[graph.keyframes]
redundant_thresh = 0.0
[outputs]
plots = false
"""
