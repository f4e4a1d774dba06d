"""TUM RGB-D reader plugin (``tum``)."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_datasets(register):  # type: ignore[no-untyped-def]
    from .config import TumConfig
    from .reader import detect, make_reader

    register(
        "tum",
        make_reader,
        TumConfig,
        description="TUM RGB-D (rgb.txt/depth.txt/groundtruth.txt association, freiburg intrinsics presets)",
        detect=detect,
    )
