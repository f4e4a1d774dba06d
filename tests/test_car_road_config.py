"""configs/car_road.toml: the default pipeline with the flow frontend's road plane on (the profile chosen on tune and
unseen seeds of the car scenarios: bench/RESULTS.md, issue 13, session 2026-12-03 c) and nothing else changed."""
from pathlib import Path

from pvslam_core.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def test_car_road_config_is_the_default_with_the_road_plane():
    cfg = load_config(ROOT / "configs" / "car_road.toml")
    default = load_config(None)
    fe, fd = cfg.models["frontend"], default.models["frontend"]
    assert not fd.road_plane and fe.road_plane and fe.road_margin == 1.1
    assert fe.road_verify and fe.road_max_gap == 5  # the variant chosen on unseen seeds 48-50
    assert fe.road_depth_weight == 1.0  # the road's depth prior (chosen on tune seeds, checked on fresh 51-53)
    assert fe.model_copy(update={"road_plane": False, "road_margin": fd.road_margin, "road_verify": False}) == fd
    for name in ("optimizer", "segmenter", "loop", "vps"):
        assert cfg.models.get(name) == default.models.get(name), name
    assert cfg.pipeline.graph == default.pipeline.graph and cfg.pipeline.dataset == default.pipeline.dataset
