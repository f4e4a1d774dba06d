"""configs/street_no_segmenter.toml: a street with large vehicles and no segmenter runs the default pipeline, whose
flow frontend has the texture term on and whose initialiser counts confident pixels relative to the pair's weights
(what protects such a street without labels: bench/RESULTS.md)."""
from pathlib import Path

from pvslam_core.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def test_street_config_is_the_default_without_a_segmenter():
    cfg = load_config(ROOT / "configs" / "street_no_segmenter.toml")
    default = load_config(None)
    for c in (cfg, default):
        assert c.models["frontend"].texture_tau == 1e-3 and c.models["frontend"].texture_quantile == 0.75
        assert c.pipeline.graph.init_relative_confidence
    assert cfg.pipeline.segmenter.plugin == "none" and cfg.pipeline.vps.plugin == "none"
    assert cfg.models["frontend"] == default.models["frontend"] and cfg.pipeline.graph == default.pipeline.graph
