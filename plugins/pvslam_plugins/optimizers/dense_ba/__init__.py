"""Dense bundle adjustment over keyframe poses and per-pixel inverse depths, in two schedules.

One optimizer (:class:`.optimizer.DenseBAOptimizer`), registered under two names that differ only in their
default schedule (:mod:`.config`):

* ``online_ba`` - PV-SLAM's online BA: every new keyframe runs a sliding-window BA over the last ``window`` (10)
  keyframes with 3 Gauss-Newton iterations; a short global refinement (``final.iters`` 4, one round) at the end.
* ``offline_ba`` - DROID-SLAM's schedule: a small local BA per keyframe (``window`` 7, frontend constants) and a
  global BA over every keyframe at the end (``final.rounds`` 2 x ``final.iters`` 8, backend constants).

Both close loops the same way (Sim(3) pose graph when the drift is large, then a relaxed loop BA).  So "online vs
offline BA" is ``optimizer.plugin = "online_ba" | "offline_ba"``, and any schedule in between is a config.
"""
from pvslam_core.registry import hookimpl


@hookimpl
def register_optimizers(register):
    from .config import OfflineBAConfig, OnlineBAConfig
    from .optimizer import make_dense_ba

    register("online_ba", make_dense_ba, OnlineBAConfig,
             description="PV-SLAM online BA: sliding-window dense BA (Schur complement over inverse depths) on every "
             "keyframe, Sim(3) pose graph + relaxed BA on loops, short global refinement at the end")
    register("offline_ba", make_dense_ba, OfflineBAConfig,
             description="DROID-SLAM schedule: small local BA per keyframe, global BA over all keyframes at the "
             "end; Sim(3) pose graph + relaxed BA on loops")
