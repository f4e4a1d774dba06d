"""Built-in synthetic dataset plugin (``synthetic``): generator with exact ground truth + reader.

See ``README.md`` beside this file for the scenarios and the on-disk layout.
"""
from pvslam_core.registry import hookimpl


@hookimpl
def register_datasets(register):  # type: ignore[no-untyped-def]
    from .config import SyntheticConfig
    from .generator import SCENARIOS, generate
    from .reader import detect, make_reader

    register(
        "synthetic",
        make_reader,
        SyntheticConfig,
        description="built-in synthetic sequences (driving, moving vehicles, indoor, benchmark scenarios) with exact "
        "ground truth",
        generate=generate,
        scenarios=SCENARIOS,
        detect=detect,
    )
