"""Frontends (:class:`pvslam_core.interfaces.Frontend`): turn frame-graph edges into flow targets and weights.

* ``flow`` (:mod:`pvslam_plugins.frontends.flow`): classical OpenCV DIS optical flow, the default.

Learned frontends (DROID/PVO-style update operators) plug in through the same interface; the panoptic-aware
confidence (PV-SLAM eq. 4) they share lives in :mod:`pvslam_core.slam.confidence`.
"""
