import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "core"))  # the test-only plugins (fakes.py)


@pytest.fixture
def fake_registry():
    import fakes
    from pvslam_core.registry import build_registry

    return build_registry(extra_modules=(fakes,))


@pytest.fixture
def fake_config_file(tmp_path):
    import fakes

    p = tmp_path / "pipeline.toml"
    p.write_text(fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix()))
    return p
