"""``offline_ba`` optimizer plugin: DROID-SLAM style small local BA per keyframe, global BA at the end."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_optimizers(register):
    from .optimizer import OfflineBAConfig, make_offline_ba

    register(
        "offline_ba",
        make_offline_ba,
        OfflineBAConfig,
        description="DROID-SLAM style: small local BA per keyframe (frontend constants), global BA over all "
        "keyframes in finalize (backend constants); Sim(3) pose graph + relaxed BA on loops",
    )
