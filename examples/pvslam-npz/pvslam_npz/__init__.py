"""Example third-party pvslam plugin: a dataset reader for one-file ``.npz`` sequences."""
from pvslam_core.registry import hookimpl

__version__ = "0.1.0"


@hookimpl
def register_datasets(register):
    from .reader import NpzConfig, NpzReader

    def factory(config, context):
        return NpzReader(config)

    register("npz", factory, NpzConfig, description="a sequence stored in one .npz file (example plugin)")


def write_npz(path, frames):
    from .reader import write_npz as _write

    return _write(path, frames)
