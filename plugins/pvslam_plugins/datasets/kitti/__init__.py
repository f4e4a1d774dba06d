"""KITTI odometry reader plugin (``kitti``)."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_datasets(register):  # type: ignore[no-untyped-def]
    from .config import KittiConfig
    from .reader import detect, make_reader

    register(
        "kitti",
        make_reader,
        KittiConfig,
        description="KITTI odometry: sequences/NN/image_0|image_2, calib.txt, times.txt, poses/NN.txt",
        detect=detect,
    )
