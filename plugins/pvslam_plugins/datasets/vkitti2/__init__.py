"""Virtual KITTI 2 reader plugin (``vkitti2``)."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_datasets(register):  # type: ignore[no-untyped-def]
    from .config import Vkitti2Config
    from .reader import make_reader

    register(
        "vkitti2",
        make_reader,
        Vkitti2Config,
        description="Virtual KITTI 2 (rgb, depth, class+instance segmentation as panoptic, intrinsics/extrinsics)",
    )
