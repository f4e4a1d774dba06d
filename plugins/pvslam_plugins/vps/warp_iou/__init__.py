"""``warp_iou`` VPS head: temporally consistent panoptic ids without weights.

The previous frame's tracked ids are forward-warped into the current frame (with the VO flow from the motion cue,
or OpenCV DIS flow between the two images; stuff optionally with depth + camera poses; z-ordered by depth when
known), then each current *thing* segment takes the id of the best-overlapping warped previous segment of the same
category (greedy, one-to-one, score = |g & p| / |p| as in PVO, or IoU, above ``min_score``); the rest get new ids
``category_id * 1000 + counter`` that are never reused.  Stuff gets ``category_id * 1000``.

Registered as VPS plugin ``warp_iou``.
"""
from __future__ import annotations

from pvslam_core.registry import hookimpl


@hookimpl
def register_vps_heads(register):  # type: ignore[no-untyped-def]
    from .config import WarpIoUConfig
    from .head import make_vps_head

    register(
        "warp_iou",
        make_vps_head,
        WarpIoUConfig,
        description="forward-warp previous ids (VO flow / DIS / depth+pose) + greedy same-category overlap matching",
    )
