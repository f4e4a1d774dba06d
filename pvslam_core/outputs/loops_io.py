"""``run_dir/loops.json``: detected loop closures.

Format::

    {"loops": [{"frame_i": 410, "frame_j": 30, "kf_i": 41, "kf_j": 3, "score": 0.91, "verified": true,
                "inliers": 120, "loop_ba": true}, ...]}

``frame_i`` / ``frame_j`` are the input-frame indices (newer, older) - what loop evaluation against ground-truth
revisit pairs uses; ``kf_i`` / ``kf_j`` the stable keyframe ids (:class:`~pvslam_core.types.LoopClosure`).  Files
may instead carry ``i`` / ``j`` keyframe indices plus a keyframe -> frame mapping given to the writer.
"""
from __future__ import annotations

import os
from typing import Any, Optional, Sequence

import numpy as np

from .metrics import read_json, write_json_atomic

__all__ = ["write_loops", "read_loops", "loop_frame_pairs"]


def write_loops(path: str | os.PathLike, loops: Sequence[Any], keyframe_frame_index: Optional[Any] = None) -> None:
    """Write loops (``LoopClosure`` objects, dicts, objects with ``i``/``j`` or ``(i, j)`` tuples) atomically.

    ``keyframe_frame_index``: int ``[K]`` input-frame index of each keyframe, to add ``frame_i`` / ``frame_j``.
    """
    kf = None
    if keyframe_frame_index is not None:
        kf = keyframe_frame_index.detach().cpu().numpy() if hasattr(keyframe_frame_index, "detach") else keyframe_frame_index
        kf = np.asarray(kf, dtype=np.int64).reshape(-1)
    out = []
    for lp in loops:
        if isinstance(lp, dict):
            d = dict(lp)
        elif hasattr(lp, "frame_i") and hasattr(lp, "kf_i"):  # LoopClosure
            d = {k: getattr(lp, k) for k in ("frame_i", "frame_j", "kf_i", "kf_j", "score", "verified", "inliers",
                                             "loop_ba")}
        elif hasattr(lp, "i") and hasattr(lp, "j"):
            d = {"i": int(lp.i), "j": int(lp.j)}
            for k in ("score", "verified", "inliers"):
                if hasattr(lp, k):
                    d[k] = getattr(lp, k)
        else:
            a, b = lp
            d = {"i": int(a), "j": int(b)}
        if kf is not None and "frame_i" not in d:
            for key, fkey in (("i", "frame_i"), ("j", "frame_j")):
                k = int(d[key])
                if not 0 <= k < len(kf):
                    raise ValueError(f"write_loops: keyframe index {k} out of range for {len(kf)} keyframes")
                d[fkey] = int(kf[k])
        out.append(d)
    write_json_atomic(path, {"loops": out})


def read_loops(path: str | os.PathLike) -> list[dict]:
    data = read_json(path)
    loops = data.get("loops", []) if isinstance(data, dict) else data
    out = []
    for lp in loops:
        out.append(dict(lp) if isinstance(lp, dict) else {"i": int(lp[0]), "j": int(lp[1])})
    return out


def loop_frame_pairs(loops: Sequence[dict], keyframe_frame_index: Optional[Any] = None) -> list[tuple[int, int]]:
    """``(frame_i, frame_j)`` input-frame pairs of loops from :func:`read_loops` (``frame_*`` keys when present,
    else ``i`` / ``j`` mapped through ``keyframe_frame_index``, else ``i`` / ``j`` as they are)."""
    kf = None if keyframe_frame_index is None else np.asarray(keyframe_frame_index, dtype=np.int64).reshape(-1)
    pairs = []
    for d in loops:
        if "frame_i" in d and "frame_j" in d:
            pairs.append((int(d["frame_i"]), int(d["frame_j"])))
        elif kf is not None:
            pairs.append((int(kf[int(d["i"])]), int(kf[int(d["j"])])))
        else:
            pairs.append((int(d["i"]), int(d["j"])))
    return pairs
