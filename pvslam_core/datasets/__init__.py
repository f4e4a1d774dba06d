"""Dataset-reader support shared by the reader plugins: the base class, options, calibration and file helpers."""
from .base import BaseReader, DatasetError, ReaderOptions, compute_geometry, transform_frame
from .calib import intrinsics_from_values, read_calibration, read_calibration_values

__all__ = [
    "BaseReader",
    "DatasetError",
    "ReaderOptions",
    "compute_geometry",
    "transform_frame",
    "intrinsics_from_values",
    "read_calibration",
    "read_calibration_values",
]
