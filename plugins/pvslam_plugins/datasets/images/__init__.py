"""Image-folder reader plugin (``images``)."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_datasets(register):  # type: ignore[no-untyped-def]
    from .config import ImagesConfig
    from .reader import detect, make_reader

    register(
        "images",
        make_reader,
        ImagesConfig,
        description="A folder of images plus a calibration (fx fy cx cy [k1 k2 p1 p2 [k3]])",
        detect=detect,
    )
