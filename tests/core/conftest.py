import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))


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


@pytest.fixture
def archived_run(tmp_path, fake_registry, monkeypatch):
    """A run on an npz sequence with ground-truth revisits, copied elsewhere, and its sequence deleted."""
    import shutil

    import fakes
    from pvslam_core.api import run_config
    from pvslam_npz import write_npz

    seq = write_npz(tmp_path / "seq.npz", fakes.FakeDataset(fakes.FakeDatasetConfig(frames=12)))
    spec = fake_registry.get("dataset", "npz")
    make = spec.factory

    def with_loops(c, ctx):  # the npz reader knows no revisits; give it two so loop GT must be archived too
        reader = make(c, ctx)
        info = reader.info
        reader.info = lambda: type(info())(**{**info().__dict__, "loop_pairs": [(10, 2), (11, 3)]})
        return reader

    monkeypatch.setattr(spec, "factory", with_loops)
    cfg = tmp_path / "npz.toml"
    cfg.write_text(fakes.FAKE_PIPELINE.format(output_dir=(tmp_path / "runs").as_posix())
                   .replace('plugin = "fake"\nframes = 12', f'plugin = "npz"\npath = "{seq.as_posix()}"'))
    res = run_config(cfg, registry=fake_registry)
    original = json.loads((Path(res.run_dir) / "metrics.json").read_text())
    copy = tmp_path / "archive" / "my-run"
    shutil.copytree(res.run_dir, copy)
    seq.unlink()
    (copy / "metrics.json").unlink()
    return copy, original
