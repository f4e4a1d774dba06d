"""The PV-SLAM pipeline (the paper's Algorithm 1) driven against the core interfaces only.

For every input frame::

    seg   = segmenter.segment(frame)                 # initial panoptic segmentation
    track = frontend.track(frame, seg)               # motion filter
    if keyframe:
        add to the frame graph, connect (neighbour + proximity edges)
        repeat frontend.iterations times: obs = frontend.observe(edges); optimizer.step(obs)   # online BA
        loops = loop_detector.add_keyframe(...)      # a loop i<->j adds edges (i, j-1), (i, j), (i, j+1)
        if loops: optimizer.loop(...)                # relaxed loop BA (+ optional Sim(3) pose graph)
        non-keyframes since the previous keyframe get motion-only BA poses
    vps_state = vps.update(vps_state, frame, seg, ...)   # temporally consistent panoptic ids
at the end: optimizer.finalize(...) (offline global BA), outputs, evaluation.

The pipeline never calls a hook per frame: plugins are built once from the registry and called directly.
Poses are T_wc ``[t, q_xyzw]`` (see :mod:`pvslam_core.types`).
"""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Any, Optional

import torch

from .config import ResolvedConfig
from .interfaces import BuildContext, MotionCue, VPSState
from .registry import get_registry
from .types import RunResult

LOG = logging.getLogger("pvslam")


class PipelineError(RuntimeError):
    """The pipeline cannot go on; the message says why (outputs written so far are kept)."""


def _progress(total: Optional[int], enabled: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=not (enabled and sys.stderr.isatty()),
                dynamic_ncols=True, leave=False)


class Pipeline:
    """Builds the configured plugins and runs Algorithm 1 over the dataset."""

    def __init__(self, config: ResolvedConfig, run_dir: Optional[Path] = None, registry=None):
        self.cfg = config
        self.pcfg = config.pipeline
        self.registry = registry or get_registry()
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.device = torch.device(self.pcfg.run.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise PipelineError(f"run.device = {self.pcfg.run.device!r} but CUDA is not available; use 'cpu'")
        ctx = BuildContext(device=self.device, run_dir=str(self.run_dir) if self.run_dir else None,
                           seed=self.pcfg.run.seed, ba_downsample=self.pcfg.graph.ba_downsample)
        self.dataset = self._build("dataset", ctx)
        self.segmenter = self._build("segmenter", ctx)
        self.frontend = self._build("frontend", ctx)
        self.loop_detector = self._build("loop", ctx)
        self.optimizer = self._build("optimizer", ctx)
        self.vps = self._build("vps", ctx)

    def _build(self, name: str, ctx: BuildContext):
        comp = getattr(self.pcfg, name)
        if not comp.enabled:
            return None
        spec = self.registry.get(name, comp.plugin)
        return spec.factory(self.cfg.models[name], ctx)

    # ------------------------------------------------------------------------------------------- run --
    def run(self) -> RunResult:
        from .slam.mapper import Mapper
        from .run_outputs import RunOutputs

        torch.manual_seed(self.pcfg.run.seed)
        import cv2

        cv2.setRNGSeed(self.pcfg.run.seed)  # RANSAC (two-view init, loop verification) draws from OpenCV's RNG
        if self.pcfg.run.threads > 0:
            torch.set_num_threads(self.pcfg.run.threads)
        info = self.dataset.info()
        gcfg = self.pcfg.graph
        ds = gcfg.ba_downsample
        if info.intrinsics.width % ds or info.intrinsics.height % ds:
            raise PipelineError(
                f"image size {info.intrinsics.width}x{info.intrinsics.height} is not a multiple of "
                f"graph.ba_downsample={ds}; set dataset.crop_multiple={ds} (or resize)")
        mapper = Mapper(self.pcfg, info, self.frontend, self.optimizer, self.loop_detector, self.device)
        outputs = RunOutputs(self.run_dir, self.pcfg, info) if self.run_dir is not None else None
        total = info.num_frames if self.pcfg.run.max_frames is None else min(info.num_frames, self.pcfg.run.max_frames)
        LOG.info("sequence %s: %d frames %dx%d", info.name, total, info.intrinsics.width, info.intrinsics.height)
        vps_state: Optional[VPSState] = None
        t_start = time.perf_counter()
        n_frames = 0
        frame_seconds: list[float] = []
        stage = dict.fromkeys(("read", "segment", "map", "vps", "outputs", "finalize"), 0.0)  # seconds per stage
        try:
            with _progress(total, self.pcfg.run.progress, "pvslam") as bar:
                t_prev = time.perf_counter()
                for frame in self.dataset:
                    if n_frames >= total:
                        break
                    t0 = time.perf_counter()
                    stage["read"] += t0 - t_prev
                    seg = self.segmenter.segment(frame) if self.segmenter is not None else None
                    t1 = time.perf_counter()
                    new_kf = mapper.process(frame, seg)
                    t2 = time.perf_counter()
                    panoptic = None  # this frame's temporally consistent panoptic segmentation
                    if self.vps is not None and seg is not None:
                        vps_state = self.vps.update(vps_state, frame, seg, MotionCue())
                        panoptic = vps_state.panoptic
                    t3 = time.perf_counter()
                    if outputs is not None:
                        if panoptic is not None:
                            outputs.panoptic(frame, panoptic)
                        outputs.frame(frame, seg)
                        if new_kf and mapper.graph.n % self.pcfg.run.checkpoint_every == 0:
                            outputs.checkpoint(mapper)
                    n_frames += 1
                    now = time.perf_counter()
                    stage["segment"] += t1 - t0
                    stage["map"] += t2 - t1
                    stage["vps"] += t3 - t2
                    stage["outputs"] += now - t3
                    frame_seconds.append(now - t_prev)
                    t_prev = now
                    bar.update(1)
                    if n_frames % 50 == 0:
                        bar.set_postfix(kf=mapper.graph.n, loops=len(mapper.loops))
            t_fin = time.perf_counter()
            mapper.finalize()
            stage["finalize"] = time.perf_counter() - t_fin
        except BaseException as exc:  # keep what was written, then re-raise (Ctrl-C included)
            LOG.error("run stopped after %d frames: %s: %s", n_frames, type(exc).__name__, exc)
            if outputs is not None:
                try:
                    outputs.checkpoint(mapper)
                    outputs.close(mapper, partial=True)
                except Exception as inner:  # never mask the original error
                    LOG.error("could not save partial outputs: %s", inner)
            raise
        elapsed = time.perf_counter() - t_start
        ts, poses = mapper.trajectory()
        timing = {
            "frames": n_frames,
            "keyframes": mapper.graph.n,
            "seconds": elapsed,
            "fps": n_frames / elapsed if elapsed > 0 else float("nan"),
            "tracking_failures": mapper.failures,
            "reinitialisations": mapper.reinits,
            "stage_seconds": {k: round(v, 3) for k, v in stage.items()},  # read = dataset iteration
        }
        metrics: dict[str, Any] = {"timing": timing}
        if outputs is not None:
            outputs.checkpoint(mapper)
            outputs.close(mapper)
            metrics = outputs.evaluate(mapper, timing, self.dataset)
        return RunResult(
            run_dir=str(self.run_dir) if self.run_dir else None,
            timestamps=ts,
            poses=poses,
            keyframe_indices=mapper.graph.frame_index.cpu().clone(),
            keyframe_poses=mapper.graph.poses.double().cpu().clone(),
            metrics=metrics,
            loops=list(mapper.loops),
            frame_seconds=frame_seconds,
        )


def run(config: ResolvedConfig, run_dir: Optional[Path | str] = None, registry=None,
        overrides: Optional[dict[str, Any]] = None, make_dir: bool = True) -> RunResult:
    """Run a resolved config. With ``make_dir`` a new run directory is created under ``run.output_dir``."""
    from .rundir import RunLog, init_run_dir, make_run_dir

    registry = registry or get_registry()
    rcfg = config.pipeline.run
    if run_dir is None and make_dir:
        run_dir = make_run_dir(rcfg.output_dir, rcfg.name)
    if run_dir is not None:
        run_dir = Path(run_dir)
        init_run_dir(run_dir, config, registry, overrides or {})
    with RunLog(run_dir, rcfg.log_level):
        pipe = Pipeline(config, run_dir, registry)
        return pipe.run()
