"""Video-file reader plugin (``video``)."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_datasets(register):  # type: ignore[no-untyped-def]
    from .config import VideoConfig
    from .reader import make_reader

    register("video", make_reader, VideoConfig, description="A video file (cv2.VideoCapture) plus a calibration")
