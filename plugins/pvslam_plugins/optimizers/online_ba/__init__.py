"""``online_ba`` optimizer plugin: sliding-window dense BA on every keyframe (PV-SLAM's online BA)."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_optimizers(register):
    from .optimizer import OnlineBAConfig, make_online_ba

    register(
        "online_ba",
        make_online_ba,
        OnlineBAConfig,
        description="sliding-window dense BA (Schur complement over inverse depths) on every keyframe, "
        "Sim(3) pose graph + relaxed BA on loops, short global refinement at the end",
    )
