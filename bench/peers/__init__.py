"""Peer baselines for pvslam's benchmark.

- :func:`run_textbook_vo` — textbook OpenCV monocular VO (LK tracks, essential-matrix init, PnP, no BA).
- :func:`run_colmap` — COLMAP incremental SfM through ``pycolmap`` (bench-only dependency, imported lazily).
- :func:`load_sequence`, :func:`ate_sim3` — shared sequence loading and Sim(3) ATE.

All poses are camera-to-world ``T_wc`` ``[tx, ty, tz, qx, qy, qz, qw]``.
"""

from .common import ate_sim3, load_sequence
from .textbook_vo import VOConfig, run_textbook_vo


def run_colmap(*args, **kwargs):
    """Lazy wrapper of :func:`bench.peers.colmap_peer.run_colmap` (pycolmap is imported only when called)."""
    from .colmap_peer import run_colmap as _run

    return _run(*args, **kwargs)


__all__ = ["ate_sim3", "load_sequence", "run_textbook_vo", "VOConfig", "run_colmap"]
