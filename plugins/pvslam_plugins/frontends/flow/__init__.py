"""``flow``: the classical frontend (OpenCV DIS optical flow, forward-backward confidence, panoptic-aware weights).

The default frontend of ``pvslam run``.  Registered through the ``pvslam`` entry point ``flow``.

Modules
-------
* :mod:`.config`          - ``[frontend]``: ``rounds`` and the tables ``dis``, ``keyframes``, ``road``, ``dynamic``.
* :mod:`.frontend`        - :class:`~.frontend.FlowFrontend` (:class:`pvslam_core.interfaces.Frontend`): keyframe
  images, the edge cache by stable ids, tracking and observing; composed of the parts below.
* :mod:`.pair_flow`       - :class:`~.pair_flow.FlowPairs`: DIS flows of a pair, BA targets and confidences.
* :mod:`.track_starts`    - :class:`~.track_starts.TrackStarts`: where tracking DIS starts, and its recovery.
* :mod:`.dynamic_masking` - :class:`~.dynamic_masking.DynamicMasking`: per-edge / per-keyframe masks, eq. 4 weights.
* :mod:`.road_prior`      - :class:`~.road_prior.RoadPrior`: the road plane's flows and the BA's road priors.
* :mod:`.flow_ops`, :mod:`.lanes`, :mod:`.dynamic`, :mod:`.recover`, :mod:`.road_plane` - the building blocks
  (numpy / OpenCV / torch functions and small classes without frontend state).
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
