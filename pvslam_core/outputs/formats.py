"""Output formats, one line each: adding a format is a writer function in a module of this package plus its line
in one of the two tables here.

* ``EXPORT_FORMATS``: what ``pvslam export RUN_DIR --format NAME`` writes from a finished run directory (the command
  line's ``--format`` choices and help come from this table).  A writer is ``writer(run_dir, out_dir, keyframes) ->
  summary dict``; ``keyframes`` is what :func:`.keyframes_io.read_keyframes` returns when the format needs the run's
  keyframe cameras (then the keyframe images are written beside it, see :func:`.export.export_run`), else None.
* ``MAP_WRITERS``: what a run writes of its final map into the run directory (:meth:`pvslam_core.run_outputs.
  RunOutputs.close`), in table order.  A writer is ``writer(run) -> optional summary``, where ``run`` is a
  :class:`MapOutput` (run directory, the map's keyframe snapshot, categories, output settings); ``enabled`` names
  the ``[outputs]`` switch that turns it on (a new format adds its switch to ``OutputsSection``, or reuses one).

This module imports nothing heavy: the command line reads it at start.
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module
from typing import Any, Callable

__all__ = ["ExportFormat", "EXPORT_FORMATS", "MapWriter", "MapOutput", "MAP_WRITERS"]


@dataclass(frozen=True)
class ExportFormat:
    name: str
    writer: str  # "module:function", imported when used (".module": a module of this package)
    keyframes: bool  # reads keyframes/ (poses, depth, intrinsics) and writes the keyframe images
    help: str

    def load(self) -> Callable[..., dict[str, Any]]:
        module, function = self.writer.split(":")
        return getattr(import_module(module, __package__), function)


EXPORT_FORMATS: dict[str, ExportFormat] = {f.name: f for f in (
    ExportFormat("colmap", ".colmap:export_colmap", True, "cameras/images/points3D.txt, multi-view tracks"),
    ExportFormat("nerfstudio", ".nerfstudio:export_nerfstudio", True, "transforms.json + depth PNGs at image size"),
    ExportFormat("tum-aligned", ".export:export_tum_aligned", False, "trajectory.txt Sim(3)-aligned to groundtruth.txt"),
)}


@dataclass(frozen=True)
class MapOutput:
    """What a map writer gets: the run directory, the map's keyframes (:class:`~pvslam_core.slam.map_state.
    KeyframeSnapshot`), the panoptic categories, the ``[outputs]`` settings, the input's intrinsics and the source
    names of the input frames (index -> name)."""

    dir: Any
    keyframes: Any
    categories: list
    outputs: Any
    intrinsics: Any
    names: dict


@dataclass(frozen=True)
class MapWriter:
    file: str  # the file named in a write error (relative to the run directory)
    writer: str  # "module:function", imported when used
    enabled: str  # the [outputs] switch that turns it on
    help: str

    def load(self) -> Callable[..., Any]:
        module, function = self.writer.split(":")
        return getattr(import_module(module, __package__), function)


MAP_WRITERS: tuple[MapWriter, ...] = (
    MapWriter("cloud_rgb.ply", ".cloud:write_run_clouds", "ply", "cloud_rgb.ply and cloud_panoptic.ply"),
    MapWriter("keyframes/keyframes.json", ".keyframes_io:write_run_keyframes", "keyframe_depth",
              "keyframes/NNNNNN_depth.npy and keyframes.json"),
)
