"""COLMAP incremental SfM (through ``pycolmap`` 4.x) as a peer baseline for pvslam's benchmark.

Pipeline (pycolmap's Python API only, no ``colmap`` CLI):

1. ``pycolmap.extract_features``: SIFT on the CPU, one shared camera (``CameraMode.SINGLE``) with the known
   ``PINHOLE`` intrinsics from ``calib.txt`` (``ImageReaderOptions.camera_model/camera_params``).
2. Matching: ``sequential`` (default; ``match_sequential`` with an overlap of ``overlap`` frames, loop detection
   off because no vocabulary tree can be fetched offline) or ``exhaustive`` (``match_exhaustive``; quadratic,
   only sensible for ≲150 frames).
3. ``pycolmap.incremental_mapping`` with the intrinsics held fixed (no refinement of focal length, principal
   point or extra parameters, neither in bundle adjustment nor in absolute-pose registration).
4. The largest reconstruction is kept; each registered image's ``cam_from_world`` (world-to-camera ``Rigid3d``;
   ``rotation.quat`` is ``[x, y, z, w]`` in pycolmap 4.x) is inverted into ``T_wc``
   ``[tx, ty, tz, qx, qy, qz, qw]`` and mapped back to its frame index by image name. Frames COLMAP did not
   register get NaN rows.

``pycolmap`` is a bench-only dependency (pyproject extra ``bench``); it is imported when :func:`run_colmap` runs.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Optional

import numpy as np

from .common import load_sequence

__all__ = ["run_colmap", "reconstruction_poses_wc"]


def reconstruction_poses_wc(rec, names: list[str]) -> np.ndarray:
    """Poses ``T_wc`` [len(names), 7] of the images of ``rec`` named ``names`` (NaN when not registered)."""
    index = {n: k for k, n in enumerate(names)}
    out = np.full((len(names), 7), np.nan)
    for image in rec.images.values():
        k = index.get(image.name)
        if k is None or not image.has_pose:
            continue
        cam_from_world = image.cam_from_world()
        if callable(getattr(cam_from_world, "inverse", None)):
            world_from_cam = cam_from_world.inverse()
        else:  # pragma: no cover - older bindings
            world_from_cam = cam_from_world.inverse
        out[k, :3] = np.asarray(world_from_cam.translation, dtype=np.float64)
        out[k, 3:] = np.asarray(world_from_cam.rotation.quat, dtype=np.float64)  # xyzw
    return out


def run_colmap(
    seq_dir,
    work_dir,
    max_frames: Optional[int] = None,
    *,
    matching: str = "sequential",
    overlap: int = 15,
    quadratic_overlap: bool = True,
    max_num_features: int = 4096,
    first_octave: int = -1,
    num_threads: int = -1,
    seed: int = 0,
    max_runtime_s: Optional[float] = None,
    mapper_options: Optional[dict] = None,
    reuse_database: bool = False,
    verbose: bool = False,
) -> dict:
    """Run COLMAP incremental SfM on a sequence folder.

    Args:
        seq_dir: TUM-style sequence folder (``rgb/``, ``rgb.txt``, ``calib.txt``; ``groundtruth.txt`` optional).
        work_dir: scratch folder (database, sparse models); its ``database.db`` and ``sparse/`` are replaced.
        max_frames: use only the first ``max_frames`` frames.
        matching: ``"sequential"`` or ``"exhaustive"``.
        overlap: number of following frames each frame is matched to (sequential matching).
        quadratic_overlap: also match frames at offsets 2^k beyond the overlap (COLMAP's default; the longer
            baselines help forward motion).
        max_num_features: SIFT features per image.
        first_octave: SIFT's first octave (-1: upsample the image first, COLMAP's default; 0 is ~3x faster).
        num_threads: threads for extraction/matching/mapping (-1: all).
        seed: random seed for the mapper (determinism).
        max_runtime_s: stop the incremental mapper after this many seconds (what it has is kept).
        mapper_options: extra ``IncrementalPipelineOptions`` attributes, dotted names allowed, e.g.
            ``{"ba_global_frames_ratio": 1.4, "mapper.init_min_tri_angle": 8.0}``.
        reuse_database: keep an existing ``work_dir/database.db`` (features and matches of an earlier run with the
            same frames) and only re-run the mapper; ``timings`` then has no extract/match entries.
        verbose: keep COLMAP's (glog) logging to stderr.

    Returns ``dict(timestamps [N], poses [N, 7] T_wc with NaN rows for unregistered frames, seconds (wall),
    cpu_seconds (this process, all threads), num_registered, num_frames, num_models, num_points3D,
    timings {extract, match, map})``.
    """
    if matching not in ("sequential", "exhaustive"):
        raise ValueError(f"matching must be 'sequential' or 'exhaustive', got {matching!r}")
    import pycolmap

    seq = load_sequence(seq_dir, max_frames=max_frames)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    sparse = work / "sparse"
    reuse = bool(reuse_database) and db.exists()
    if db.exists() and not reuse:
        db.unlink()
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir()

    # All images must live under one image_path; names are relative to it.
    image_root = Path(seq.root)
    names = [p.relative_to(image_root).as_posix() for p in seq.image_paths]

    if not verbose and hasattr(pycolmap, "logging"):
        try:
            pycolmap.logging.minloglevel = 2  # warnings and errors only
        except Exception:  # pragma: no cover
            pass
    if hasattr(pycolmap, "set_random_seed"):
        pycolmap.set_random_seed(seed)

    fx, fy, cx, cy = (float(v) for v in seq.intrinsics)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{fx},{fy},{cx},{cy}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.sift.max_num_features = max_num_features
    extraction.sift.first_octave = int(first_octave)

    timings = {}
    t_start = time.perf_counter()
    c_start = time.process_time()
    if not reuse:
        pycolmap.extract_features(
            db, image_root, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
        )
        timings["extract"] = time.perf_counter() - t_start

        t0 = time.perf_counter()
        matching_opts = pycolmap.FeatureMatchingOptions()
        matching_opts.num_threads = num_threads
        if matching == "sequential":
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = int(overlap)
            pairing.quadratic_overlap = bool(quadratic_overlap)
            pairing.loop_detection = False
            pycolmap.match_sequential(db, matching_options=matching_opts, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        else:
            pycolmap.match_exhaustive(db, matching_options=matching_opts, device=pycolmap.Device.cpu)
        timings["match"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.mapper.abs_pose_refine_focal_length = False
    opts.mapper.abs_pose_refine_extra_params = False
    opts.mapper.random_seed = seed
    opts.triangulation.random_seed = seed
    if max_runtime_s is not None:
        opts.max_runtime_seconds = max(1, int(round(max_runtime_s)))  # int in pycolmap 4.x
    for key, value in (mapper_options or {}).items():
        obj = opts
        *parents, leaf = key.split(".")
        for part in parents:
            obj = getattr(obj, part)
        if not hasattr(obj, leaf):
            raise AttributeError(f"IncrementalPipelineOptions has no option {key!r}")
        setattr(obj, leaf, value)
    recs = pycolmap.incremental_mapping(db, image_root, sparse, opts)
    timings["map"] = time.perf_counter() - t0
    seconds = time.perf_counter() - t_start
    cpu_seconds = time.process_time() - c_start

    poses = np.full((len(names), 7), np.nan)
    num_points = 0
    if recs:
        best = max(recs.values(), key=lambda r: r.num_reg_images())
        poses = reconstruction_poses_wc(best, names)
        num_points = int(best.num_points3D())
    num_registered = int(np.all(np.isfinite(poses), axis=1).sum())
    return {
        "timestamps": seq.timestamps.copy(),
        "poses": poses,
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "num_registered": num_registered,
        "num_frames": len(names),
        "num_models": len(recs) if recs else 0,
        "num_points3D": num_points,
        "timings": timings,
    }
