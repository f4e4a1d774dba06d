"""configs/street_no_segmenter.toml: the measured opt-in for streets with large vehicles and no segmenter resolves to
the flow frontend's texture term and the initialiser's relative confidence (and nothing else of the default moves)."""
from pathlib import Path

from pvslam_core.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def test_street_config_turns_on_the_texture_term_and_the_relative_init_threshold():
    cfg = load_config(ROOT / "configs" / "street_no_segmenter.toml")
    default = load_config(None)
    fe, g = cfg.models["frontend"], cfg.pipeline.graph
    assert fe.texture_tau == 1e-3 and fe.texture_quantile == 0.75 and g.init_relative_confidence
    assert default.models["frontend"].texture_tau == 0.0 and not default.pipeline.graph.init_relative_confidence
    assert cfg.pipeline.segmenter.plugin == "none"
