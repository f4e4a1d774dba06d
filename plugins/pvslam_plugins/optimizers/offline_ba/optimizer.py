"""The ``offline_ba`` optimizer (DROID-SLAM style, anchors 1.4/1.6): ``step`` runs a small local BA over the last
``window`` keyframes with the frontend constants (2 iterations, lm 1e-4, ep 0.1); ``finalize`` runs a global BA
over all keyframes (only keyframe 0 fixed) on observations of every graph edge with the backend constants
(lm 1e-5, ep 1e-2), in ``final_rounds`` observe -> BA rounds of ``final_iters`` iterations."""
from __future__ import annotations

from pydantic import Field

from pvslam_core.interfaces import BuildContext

from ..common import BAConfigBase, DenseBAOptimizer


class OfflineBAConfig(BAConfigBase):
    window: int = Field(7, ge=1, description="local window: the last `window` keyframes have free poses")
    final_iters: int = Field(8, ge=0, description="Gauss-Newton iterations per global-BA round in finalize()")
    final_rounds: int = Field(2, ge=0, description="observe -> global BA rounds in finalize() (DROID's backend "
                              "runs 7 + 12 update/BA rounds; a classical frontend needs fewer)")


class OfflineBA(DenseBAOptimizer):
    config: OfflineBAConfig


def make_offline_ba(config: OfflineBAConfig, context: BuildContext | None = None) -> OfflineBA:
    return OfflineBA(config, getattr(context, "device", None))
