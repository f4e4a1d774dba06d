"""``flow``: the classical frontend (OpenCV DIS optical flow, forward-backward confidence, panoptic-aware weights).

The default frontend of ``pvslam run``.  Registered through the ``pvslam`` entry point ``flow``.
"""
from __future__ import annotations

from pvslam_core.registry import hookimpl


@hookimpl
def register_frontends(register):
    from .config import FlowFrontendConfig
    from .frontend import make_frontend

    register(
        "flow",
        make_frontend,
        FlowFrontendConfig,
        description="OpenCV DIS optical flow with forward-backward confidence and PV-SLAM eq. 4 dynamic masking",
    )
