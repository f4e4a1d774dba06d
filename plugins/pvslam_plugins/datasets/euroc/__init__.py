"""EuRoC MAV reader plugin (``euroc``)."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_datasets(register):  # type: ignore[no-untyped-def]
    from .config import EurocConfig
    from .reader import detect, make_reader

    register(
        "euroc",
        make_reader,
        EurocConfig,
        description="EuRoC MAV (ASL layout: mav0/cam0, sensor.yaml, body ground truth converted with T_BS)",
        detect=detect,
    )
