"""The formats of ``pvslam export``, one line each: adding a format is a writer function in a module of this package
plus its line here (the command line's ``--format`` choices and help come from this table).

A writer is ``writer(run_dir, out_dir, keyframes) -> summary dict``; ``keyframes`` is what
:func:`.keyframes_io.read_keyframes` returns when the format needs the run's keyframe cameras (then the keyframe
images are written beside it, see :func:`.export.export_run`), else None.  This module imports nothing heavy: the
command line reads it at start.
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module
from typing import Any, Callable

__all__ = ["ExportFormat", "EXPORT_FORMATS"]


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
    ExportFormat("colmap", ".export:export_colmap", True, "cameras/images/points3D.txt"),
    ExportFormat("nerfstudio", ".export:export_nerfstudio", True, "transforms.json + depth"),
    ExportFormat("tum-aligned", ".export:export_tum_aligned", False, "trajectory.txt Sim(3)-aligned to groundtruth.txt"),
)}
