"""SLAM state behind Algorithm 1: the frame graph and what grows it.

* :mod:`.graph`       keyframe store (stable ids, poses, inverse depths) and the edge lifecycle;
* :mod:`.mapper`      per-frame driver of the frontend, optimizer and loop detector (keyframes, BA, loops);
* :mod:`.edges`       which edges a new keyframe gets (neighbour, proximity, loop);
* :mod:`.initializer` monocular two-view initialisation;
* :mod:`.anchors`     poses of every input frame, anchored to keyframes;
* :mod:`.confidence`  the panoptic-aware confidence of eq. 4, shared by every frontend.

The pipeline (:mod:`pvslam_core.pipeline`) owns one :class:`~.mapper.Mapper`; plugins see the graph only through
the interfaces in :mod:`pvslam_core.interfaces`.
"""
