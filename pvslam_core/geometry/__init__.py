"""Geometry for pvslam, in plain torch (CPU or GPU):

* :mod:`.lie` - batched SE(3) / Sim(3): exp/log, composition, inverse, action, adjoint, interpolation.
* :mod:`.projective` - back-projection with inverse depth, reprojection with analytic Jacobians, DROID's frame
  distance.
* :mod:`.ba` - dense bundle adjustment (Schur complement over per-pixel inverse depths; a call's settings are a
  :class:`~.ba.BAOptions`), with its parts in :mod:`.ba_problem`, :mod:`.ba_schur`, :mod:`.ba_residuals`,
  :mod:`.ba_linalg`, :mod:`.ba_distance`, and the motion-only BA of single frames in :mod:`.ba_motion`.
* :mod:`.pose_graph` - Sim(3) pose-graph optimisation and loop-edge Sim(3) measurement.
* :mod:`.two_view` - OpenCV's essential-matrix RANSAC with one behaviour on every OpenCV version, and the
  depth-free translation direction of a flow (checks loop measurements).
* :mod:`.testing` - exact synthetic BA problems for tests and benchmarks.

Poses crossing these modules' public functions are camera-to-world ``T_wc [..., 7]`` (see :mod:`pvslam_core.types`).
"""
