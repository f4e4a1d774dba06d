"""configs/street_no_segmenter.toml: a street with large vehicles and no segmenter runs the default pipeline, whose
flow frontend always has the texture term on (a constant of the code now, no key to turn it off) and whose
initialiser counts confident pixels relative to the pair's weights (what protects such a street without labels)."""
from pathlib import Path

from pvslam_core.config import load_config
from pvslam_core.slam import bootstrap
from pvslam_plugins.frontends.flow import pair_flow

ROOT = Path(__file__).resolve().parents[1]


def test_street_config_is_the_default_without_a_segmenter():
    cfg = load_config(ROOT / "configs" / "street_no_segmenter.toml")
    default = load_config(None)
    assert pair_flow.TEXTURE_TAU == 1e-3 and pair_flow.TEXTURE_QUANTILE == 0.75 and bootstrap.RELATIVE_CONFIDENCE
    for c in (cfg, default):
        assert c.models["frontend"].dynamic.enabled and c.models["frontend"].road.enabled
    assert cfg.pipeline.segmenter.plugin == "none" and cfg.pipeline.vps.plugin == "none"
    assert cfg.models["frontend"] == default.models["frontend"] and cfg.pipeline.graph == default.pipeline.graph
