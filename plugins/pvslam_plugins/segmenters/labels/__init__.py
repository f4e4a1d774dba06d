"""``labels`` segmenter: the dataset's ground-truth panoptic segmentation used as the segmenter output.

An oracle for ablations and tests (synthetic sequences, Virtual KITTI 2): it needs no weights, and it fails with a
clear message on datasets without panoptic ground truth.  Registered as segmenter plugin ``labels``.
"""
from __future__ import annotations

from pvslam_core.registry import hookimpl


@hookimpl
def register_segmenters(register):  # type: ignore[no-untyped-def]
    from .segmenter import LabelsSegmenterConfig, make_segmenter

    register(
        "labels",
        make_segmenter,
        LabelsSegmenterConfig,
        description="oracle: the dataset's ground-truth panoptic labels (needs a dataset with panoptic GT)",
        needs_gt_panoptic=True,  # the core switches it off (or picks a ready learned segmenter) on unlabelled data
    )
