"""Video-file reader plugin (``video``)."""
from pvslam_core.registry import hookimpl


@hookimpl
def register_datasets(register):  # type: ignore[no-untyped-def]
    from .config import VideoConfig
    from .reader import detect, make_reader

    register("video", make_reader, VideoConfig, description="A video file or a camera (cv2.VideoCapture) plus a "
             "calibration", detect=detect)
