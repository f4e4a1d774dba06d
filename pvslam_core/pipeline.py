"""The PV-SLAM pipeline (the paper's Algorithm 1) driven against the core interfaces only.

For every input frame (:meth:`Pipeline.step`)::

    seg    = segmenter.segment(frame)                 # initial panoptic segmentation
    result = mapper.process(frame, seg, next frame)   # VO: motion filter; on a keyframe: edges, online BA,
                                                      # loop closure (i, j-1), (i, j), (i, j+1) + relaxed loop BA,
                                                      # motion-only BA of the frames since the last keyframe
    cue    = motion_cue(previous result, result)      # VO flow, depth and poses between the two frames
    vps    = vps.update(vps, frame, seg, cue)         # temporally consistent panoptic ids
at the end (:meth:`Pipeline.finish`): optimizer.finalize (offline global BA), outputs, evaluation.

The pipeline never calls a hook per frame: plugins are built once from the registry and called directly.
:meth:`Pipeline.run` iterates the configured dataset; :meth:`start` / :meth:`step` / :meth:`finish` serve callers
that feed frames themselves (:class:`pvslam_core.tracker.Tracker`).  Before the plugins are built the config is
fitted to the data (:mod:`pvslam_core.adapt`: no ``labels`` segmenter on unlabelled data).  An optional
:class:`~pvslam_core.observer.RunObserver` (a live viewer) is told of every frame, keyframe and loop.  Poses are
T_wc ``[t, q_xyzw]`` (see :mod:`pvslam_core.types`).

Threads (:mod:`pvslam_core.background`): the mapping is one thread; :meth:`run` decodes the next frames on a
reader thread (``run.read_ahead``) and, from a built-in reader of known length, hands the mapper the next frame too
(a frontend may begin its tracking beside this frame's BA: :meth:`~pvslam_core.interfaces.Frontend.prefetch`); with a
run directory the motion cue, the VPS update and the panoptic PNG of each frame run in order on an output thread
(``run.write_behind``) while the next frame is mapped -- unless an observer waits for each frame's panoptic.  Both
queues are bounded, so memory stays flat.
"""
from __future__ import annotations

import logging
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Optional

import torch

from .allocator import RELEASE_EVERY, release_freed_memory
from .config import ResolvedConfig
from .interfaces import BuildContext, VPSState
from .registry import get_registry
from .types import Frame, FrameResult, PanopticSegmentation, RunResult, SequenceInfo

LOG = logging.getLogger("pvslam")

STAGES = ("read", "segment", "map", "vps", "outputs", "finalize")


class PipelineError(RuntimeError):
    """The pipeline cannot go on; the message says why (outputs written so far are kept)."""


def failed_at(exc: BaseException) -> Optional[str]:
    """Where a run stopped on ``exc`` ("the map stage at frame 12"), as :meth:`Pipeline.run` recorded it."""
    return getattr(exc, "pvslam_where", None)


def _record_where(exc: BaseException, stage: str, index: Optional[int], frames_done: int) -> None:
    if failed_at(exc) is not None:
        return
    if stage == "read":
        where = f"the read stage after {frames_done} frames"
    else:
        where = f"the {stage} stage" + (f" at frame {index}" if index is not None else "")
    try:
        exc.pvslam_where = where
    except AttributeError:  # an exception type without attributes of its own
        pass


class RunTerminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a job scheduler): handled like Ctrl-C, outputs written so far are kept."""


def _progress(total: Optional[int], enabled: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=not (enabled and sys.stderr.isatty()),
                dynamic_ncols=True, leave=False)


@contextmanager
def _sigterm_as_interrupt():
    """Within the block, SIGTERM raises :class:`RunTerminated` (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        raise RunTerminated("terminated by SIGTERM")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


@contextmanager
def _signals_deferred():
    """Ignore SIGINT/SIGTERM while partial outputs are saved (a second Ctrl-C must not cut the save short)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


class Pipeline:
    """Builds the configured plugins and runs Algorithm 1 over the dataset (or over frames fed by the caller)."""

    def __init__(self, config: ResolvedConfig, run_dir: Optional[Path] = None, registry=None, dataset=None,
                 observer=None):
        self.cfg = config
        self.pcfg = config.pipeline
        self.registry = registry or get_registry()
        self.observer = observer  # a RunObserver (pvslam_core.observer), or None
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.device = torch.device(self.pcfg.run.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise PipelineError(f"run.device = {self.pcfg.run.device!r} but CUDA is not available; use 'cpu'")
        ctx = BuildContext(device=self.device, run_dir=str(self.run_dir) if self.run_dir else None,
                           seed=self.pcfg.run.seed, ba_downsample=self.pcfg.graph.ba_downsample)
        self.dataset = dataset if dataset is not None else self._build("dataset", ctx)
        self.info: SequenceInfo = self.dataset.info()
        ctx.info = self.info  # the other plugins may size themselves to the sequence
        from .adapt import fit_to_sequence, say_processing_size

        say_processing_size(self.info)

        # e.g. no labels segmenter on data without labels; self.cfg is what runs (and what config.json records)
        self.cfg, self.notes = fit_to_sequence(self.cfg, self.info, self.registry)
        self.pcfg = self.cfg.pipeline
        ctx.ba_downsample = self.pcfg.graph.ba_downsample  # fitted to the image size (adapt.py)
        self.segmenter = self._build("segmenter", ctx)
        self.frontend = self._build("frontend", ctx)
        self.loop_detector = self._build("loop", ctx)
        self.optimizer = self._build("optimizer", ctx)
        self.vps = self._build("vps", ctx)
        self.mapper = None
        self.outputs = None

    def _build(self, name: str, ctx: BuildContext):
        comp = getattr(self.pcfg, name)
        if not comp.enabled:
            return None
        spec = self.registry.get(name, comp.plugin)
        return spec.factory(self.cfg.models[name], ctx)

    def categories(self):
        """The categories of the panoptic output: the segmenter's own, else the dataset's."""
        cats = self.segmenter.categories() if self.segmenter is not None else None
        return list(cats) if cats else list(self.info.categories)

    # ---------------------------------------------------------------------------------------- per frame --
    def start(self) -> None:
        """Seed, thread settings, the mapper and the run directory's writers."""
        from .run_outputs import RunOutputs
        from .slam.mapper import Mapper

        torch.manual_seed(self.pcfg.run.seed)
        import cv2

        cv2.setRNGSeed(self.pcfg.run.seed)  # RANSAC (two-view init, loop verification) draws from OpenCV's RNG
        if self.pcfg.run.threads > 0:
            torch.set_num_threads(self.pcfg.run.threads)
        if self.pcfg.run.keep_freed_memory:
            from .allocator import keep_freed_memory

            keep_freed_memory()
        info = self.info
        ds = self.pcfg.graph.ba_downsample
        if info.intrinsics.width % ds or info.intrinsics.height % ds:
            raise PipelineError(
                f"image size {info.intrinsics.width}x{info.intrinsics.height} is not a multiple of "
                f"graph.ba_downsample={ds}; set dataset.crop_multiple={ds} (or resize)")
        # with a run directory, what the map reads again only at the end is kept in an unlinked file there
        self.mapper = Mapper(self.pcfg, info, self.frontend, self.optimizer, self.loop_detector, self.device,
                             spill_dir=self.run_dir)
        self.outputs = RunOutputs(self.run_dir, self.pcfg, info, self.categories()) if self.run_dir else None
        self.vps_state: Optional[VPSState] = None
        self.last: Optional[FrameResult] = None
        self.frames_done = 0
        self.frame_seconds: list[float] = []
        self.stage = dict.fromkeys(STAGES, 0.0)  # seconds per stage
        # CPU seconds per stage of the calling thread (wall time means little on a shared machine), and of the
        # whole process over the run (includes helper threads)
        self.stage_cpu = dict.fromkeys(STAGES, 0.0)
        # per kind of step (a frame that became a keyframe, any other): [steps, wall seconds, pipeline-thread CPU]
        self.steps = {"keyframe": [0, 0.0, 0.0], "other": [0, 0.0, 0.0]}
        self.t_start = time.perf_counter()
        self.cpu_start = time.process_time()
        self.ever_initialized = False
        self._loops_seen = 0
        self._at: tuple[str, Optional[int]] = ("read", None)  # the stage and frame index running (error reports)
        if self.observer is not None:
            self._notify("on_start", self.info, self.categories())

    def step(self, frame: Frame, next_frame: Optional[Frame] = None) -> FrameResult:
        """Process one frame (segmentation, mapping, VPS, outputs); returns the mapper's result for it.
        ``next_frame``: the next input frame when it is at hand (the frontend may start on it while this frame's
        map work runs; the results do not depend on it)."""
        from .slam.motion_cue import motion_cue

        t0, c0 = time.perf_counter(), time.thread_time()
        self._at = ("segment", frame.index)
        seg = self.segmenter.segment(frame) if self.segmenter is not None else None
        t1, c1 = time.perf_counter(), time.thread_time()
        self._at = ("map", frame.index)
        result = self.mapper.process(frame, seg, next_frame)
        self.ever_initialized |= result.initialized
        t2, c2 = time.perf_counter(), time.thread_time()
        panoptic: Optional[PanopticSegmentation] = None  # this frame's temporally consistent segmentation
        self._at = ("vps", frame.index)
        if self.vps is not None and seg is not None:
            # With nobody waiting for this frame's panoptic (no observer), the motion cue, the VPS and its PNG run
            # on the output thread, in frame order, while the next frame is mapped (FrameResults are not changed
            # after they are returned); else here.
            if self.observer is not None or self.outputs is None or not self.outputs.behind_submit(
                    self._vps_step, frame, seg, self.last, result):
                self.vps_state = self.vps.update(self.vps_state, frame, seg, motion_cue(self.last, result))
                panoptic = self.vps_state.panoptic
                if self.outputs is not None:
                    self.outputs.panoptic(frame, panoptic)
        self.last = result
        t3, c3 = time.perf_counter(), time.thread_time()
        self._at = ("outputs", frame.index)
        if self.outputs is not None:
            self.outputs.frame(frame, seg)
            if result.is_keyframe and self.mapper.graph.n % self.pcfg.run.checkpoint_every == 0:
                self.outputs.checkpoint(self.mapper.snapshot(), self.frames_done + 1)
        if self.observer is not None:
            self._observe(frame, result, panoptic)
        if (self.frames_done + 1) % RELEASE_EVERY == 0:
            release_freed_memory()  # free pages the BA's scratch left inside the heap go back to the OS
        self.frames_done += 1
        self._at = ("read", None)
        now, cnow = time.perf_counter(), time.thread_time()
        for name, dt in (("segment", t1 - t0), ("map", t2 - t1), ("vps", t3 - t2), ("outputs", now - t3)):
            self.stage[name] += dt
        for name, dt in (("segment", c1 - c0), ("map", c2 - c1), ("vps", c3 - c2), ("outputs", cnow - c3)):
            self.stage_cpu[name] += dt
        kind = self.steps["keyframe" if result.is_keyframe else "other"]
        kind[0], kind[1], kind[2] = kind[0] + 1, kind[1] + now - t0, kind[2] + cnow - c0
        return result

    def _vps_step(self, frame: Frame, seg: PanopticSegmentation, last: Optional[FrameResult],
                  result: FrameResult) -> None:
        """Motion cue, VPS update and panoptic PNG of one frame, on the output thread (see :meth:`step`)."""
        from .slam.motion_cue import motion_cue

        try:
            self.vps_state = self.vps.update(self.vps_state, frame, seg, motion_cue(last, result))
            self.outputs.panoptic_now(frame, self.vps_state.panoptic)
        except BaseException as exc:  # re-raised in the pipeline thread, a frame or two later: say which frame
            _record_where(exc, "vps", frame.index, self.frames_done)
            raise

    def _observe(self, frame: Frame, result: FrameResult, panoptic: Optional[PanopticSegmentation]) -> None:
        self._notify("on_frame", frame, result, panoptic)
        mapper = self.mapper
        snap = None
        if result.is_keyframe and mapper.initialized:
            snap = mapper.keyframes_snapshot()
            self._notify("on_keyframes", snap)
        loops = mapper.loops
        for loop in loops[self._loops_seen:]:
            self._notify("on_loop", loop, snap or mapper.keyframes_snapshot())
        self._loops_seen = len(loops)

    def _notify(self, method: str, *args) -> None:
        """Call the observer; one that raises is switched off (a viewer must not end the run)."""
        if self.observer is None:
            return
        try:
            getattr(self.observer, method)(*args)
        except Exception as exc:  # noqa: BLE001
            LOG.error("viewer switched off: its %s raised %s: %s", method, type(exc).__name__, exc)
            self.observer = None

    def finish(self) -> RunResult:
        """Final optimisation, outputs and evaluation."""
        mapper = self.mapper
        self._at = ("finalize", None)
        t_fin, c_fin = time.perf_counter(), time.thread_time()
        mapper.finalize()
        self.stage["finalize"] = time.perf_counter() - t_fin
        self.stage_cpu["finalize"] = time.thread_time() - c_fin
        elapsed = time.perf_counter() - self.t_start
        cpu = time.process_time() - self.cpu_start
        snap = mapper.snapshot()
        kf = snap.keyframes
        timing = {
            "frames": self.frames_done,
            "keyframes": len(kf.ids),
            "seconds": elapsed,
            "fps": self.frames_done / elapsed if elapsed > 0 else float("nan"),
            "tracking_failures": mapper.failures,
            "reinitialisations": mapper.reinits,
            "stage_seconds": {k: round(v, 3) for k, v in self.stage.items()},  # read = dataset iteration
            "cpu_seconds": round(cpu, 3),  # process CPU time (all threads), start to end of the final BA
            "stage_cpu_seconds": {k: round(v, 3) for k, v in self.stage_cpu.items()},  # the pipeline thread's
            "map_cpu_seconds": {k: round(v, 3) for k, v in sorted(mapper.cpu.items())},  # parts of "map"
            # mean wall and pipeline-thread CPU of a step (waiting for the next frame excluded), per kind of step:
            # a frame that became a keyframe grows and optimises the map, any other frame is only tracked
            "steps": {k: {"count": n, "wall_ms": round(1000 * w / max(n, 1), 2),
                          "cpu_ms": round(1000 * c / max(n, 1), 2)} for k, (n, w, c) in self.steps.items()},
        }
        tracking = {"initialized": bool(self.ever_initialized), **mapper.stats()}
        if not self.ever_initialized:
            LOG.error("no motion was estimated: the map never initialised (too little parallax, too few frames or "
                      "no texture); the trajectory holds placeholder poses")
        metrics: dict[str, Any] = {"timing": timing, "tracking": tracking}
        if self.outputs is not None:
            from .outputs.metrics import MetricsFile

            self.outputs.checkpoint(snap)
            self.outputs.close(snap)
            # before the evaluation: it reads tracking.scale_gaps (ate_segments)
            MetricsFile(self.run_dir / "metrics.json").update({"tracking": tracking})
            metrics = {**self.outputs.evaluate(timing, self.dataset), "tracking": tracking}
        result = RunResult(
            run_dir=str(self.run_dir) if self.run_dir else None,
            timestamps=snap.timestamps,
            poses=snap.poses,
            keyframe_indices=kf.frame_index.clone(),
            keyframe_poses=kf.poses.clone(),
            metrics=metrics,
            loops=list(snap.loops),
            frame_seconds=self.frame_seconds,
        )
        if self.observer is not None:
            self._notify("on_finish", result, mapper.keyframes_snapshot())
        mapper.state.spill.close()  # its disk space
        return result

    def abort(self, exc: BaseException) -> None:
        """Keep what was written: the trajectory of every completed frame and a partial metrics.json."""
        LOG.error("run stopped after %d frames: %s: %s", self.frames_done, type(exc).__name__, exc)
        if self.outputs is None or self.mapper is None:
            return
        with _signals_deferred():
            # each save on its own: a failing write (disk full) must not stop metrics.json from being written
            for save in (lambda: self.outputs.checkpoint(self.mapper.snapshot(), self.frames_done),
                         lambda: self.outputs.close(self.mapper.snapshot(trajectory=False), partial=True,
                                                    frames_done=self.frames_done)):
                try:
                    save()
                except Exception as inner:  # never mask the original error
                    LOG.error("could not save partial outputs: %s", inner)

    # ------------------------------------------------------------------------------------------- run --
    def run(self) -> RunResult:
        self.start()
        # num_frames is the progress bar's total only (None: a live source; a video container's count is a claim):
        # the run ends with the dataset's iteration, or at run.max_frames
        limit = self.pcfg.run.max_frames
        total = self.info.num_frames
        if limit is not None:
            total = limit if total is None else min(total, limit)
        LOG.info("sequence %s: %s frames %dx%d", self.info.name, "unknown number of" if total is None else total,
                 self.info.intrinsics.width, self.info.intrinsics.height)
        from contextlib import closing
        from itertools import islice

        from .background import read_ahead, with_next

        try:
            # frames are decoded on a background thread, at most run.read_ahead ahead (see background.py)
            # (only the built-in readers' BaseReader: each frame it yields is a new object, so reading ahead cannot
            # change a frame the pipeline has not processed yet; other readers are iterated in this thread)
            from .datasets.base import BaseReader

            depth = self.pcfg.run.read_ahead if isinstance(self.dataset, BaseReader) else 0
            frames = read_ahead(islice(self.dataset, limit), depth)
            with _sigterm_as_interrupt(), _progress(total, self.pcfg.run.progress, "pvslam") as bar, \
                    closing(frames):
                t_prev, c_prev = time.perf_counter(), time.thread_time()
                # a source read ahead (see above) of known length is read one frame ahead of the mapper too (the
                # frontend's prefetch); a live one is not (its next frame may not exist yet: this one would wait)
                for frame, next_frame in with_next(frames, depth > 0 and total is not None):
                    if limit is not None and self.frames_done >= limit:
                        break
                    self.stage["read"] += time.perf_counter() - t_prev
                    self.stage_cpu["read"] += time.thread_time() - c_prev
                    self.step(frame, next_frame)
                    now = time.perf_counter()
                    self.frame_seconds.append(now - t_prev)
                    t_prev, c_prev = now, time.thread_time()
                    bar.update(1)
                    if self.frames_done % 50 == 0:
                        bar.set_postfix(kf=self.mapper.graph.n, loops=len(self.mapper.loops))
                return self.finish()
        except BaseException as exc:  # keep what was written, then re-raise (Ctrl-C and SIGTERM included)
            _record_where(exc, *getattr(self, "_at", ("start", None)), self.frames_done)
            self.abort(exc)
            raise


def run(config: ResolvedConfig, run_dir: Optional[Path | str] = None, registry=None,
        overrides: Optional[dict[str, Any]] = None, make_dir: bool = True, observer=None) -> RunResult:
    """Run a resolved config. With ``make_dir`` a new run directory is created under ``run.output_dir``;
    ``observer`` (a :class:`~pvslam_core.observer.RunObserver`) watches the run."""
    from .rundir import RunLog, init_run_dir, make_run_dir, remove_unused_run_dir

    registry = registry or get_registry()
    rcfg = config.pipeline.run
    created = run_dir is None and make_dir
    if created:
        run_dir = make_run_dir(rcfg.output_dir, rcfg.name)
    pipe = None
    try:
        if run_dir is not None:
            run_dir = Path(run_dir)
            init_run_dir(run_dir, config, registry, overrides or {})
        with RunLog(run_dir, rcfg.log_level):
            try:
                pipe = Pipeline(config, run_dir, registry, observer=observer)
            except BaseException as exc:  # e.g. the dataset cannot be opened: say so in log.txt too
                LOG.error("could not start the run: %s: %s", type(exc).__name__, exc)
                raise
            if pipe.notes and run_dir is not None:  # config.json records what runs, after fitting it to the data
                init_run_dir(run_dir, pipe.cfg, registry, overrides or {})
            return pipe.run()
    except BaseException as exc:
        # a run directory of this run that holds no result (it stopped before its first frame) is not left behind
        if created and getattr(pipe, "frames_done", 0) == 0 and remove_unused_run_dir(run_dir):
            try:
                exc.pvslam_run_dir_removed = True  # error messages then do not point at it
            except AttributeError:
                pass
        raise
