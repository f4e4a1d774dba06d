"""SLAM state behind Algorithm 1: the frame graph and the parts that grow it.

* :mod:`.mapper`       the per-frame driver (Algorithm 1) over the parts below;
* :mod:`.map_state`    what the parts share (graph, frame poses, measured depth, fragments) and the snapshot;
* :mod:`.keyframes`    the keyframe policy (provisional keyframes, redundancy, removal);
* :mod:`.edges`        the edge policy (neighbour, proximity, loop edges; retirement);
* :mod:`.window_ba`    the window BA of a new keyframe (:mod:`.motion_start`: its second start after a pan);
* :mod:`.loop_closer`  loop closing (:mod:`.loops`: the loop policy; :mod:`.fragments`: merging map fragments);
* :mod:`.bootstrap`    map initialisation (:mod:`.initializer`: the two-view model choice);
* :mod:`.graph`        keyframe store (stable ids, poses, inverse depths) and the edge lifecycle;
* :mod:`.frame_poses`  poses of every input frame, anchored to keyframes;
* :mod:`.config`       the ``[graph]`` and ``[loop_closure]`` settings;
* :mod:`.confidence`   the panoptic-aware confidence of eq. 4, shared by every frontend.

The pipeline (:mod:`pvslam_core.pipeline`) owns one :class:`~.mapper.Mapper`; plugins see the graph only through
the interfaces in :mod:`pvslam_core.interfaces`.
"""
