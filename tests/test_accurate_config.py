"""configs/accurate.toml: the default pipeline with 5 Gauss-Newton iterations per window BA (more accurate, slower than
the real-time target: docs/decisions.md, optimizer.iters) and nothing else changed."""
from pathlib import Path

from pvslam_core.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def test_accurate_config_is_the_default_with_more_ba_iterations():
    cfg = load_config(ROOT / "configs" / "accurate.toml")
    default = load_config(None)
    assert default.models["optimizer"].iters == 3 and cfg.models["optimizer"].iters == 5
    assert cfg.models["optimizer"].model_copy(update={"iters": 3}) == default.models["optimizer"]
    for name in ("frontend", "segmenter", "loop", "vps"):
        assert cfg.models.get(name) == default.models.get(name), name
    assert cfg.pipeline.graph == default.pipeline.graph and cfg.pipeline.dataset == default.pipeline.dataset
