"""Old config keys: renamed ones (also into nested tables) load with a warning naming the new key; retired ones load
only with the value the method now fixes, and any other value is an error naming the key."""
from typing import ClassVar

import pytest
from pydantic import Field, ValidationError

from pvslam_core.config_base import PluginConfig


class Inner(PluginConfig):
    warmup: int = Field(5, description="keyframes before the map starts")


class Outer(PluginConfig):
    init: Inner = Field(default_factory=Inner)
    neighbours: int = Field(3, description="edges to the previous keyframes")
    renamed: ClassVar[dict] = {"warmup": "init.warmup", "radius": "neighbours", "old_thing": None}
    retired: ClassVar[dict] = {"tie_ratio": 1.25, "margin": None}


def test_renamed_keys_move_into_nested_tables_with_one_warning(caplog):
    cfg = Outer.model_validate({"warmup": 8, "radius": 2, "old_thing": 1})
    assert cfg.init.warmup == 8 and cfg.neighbours == 2
    assert "warmup -> init.warmup" in caplog.text and "radius -> neighbours" in caplog.text
    assert "old_thing" in caplog.text


def test_both_names_must_agree_and_the_input_is_not_changed():
    data = {"warmup": 6, "init": {"warmup": 6}}
    assert Outer.model_validate(data).init.warmup == 6 and data == {"warmup": 6, "init": {"warmup": 6}}
    with pytest.raises(ValidationError, match=r"'warmup' \(its old name\) and 'init.warmup' are both given"):
        Outer.model_validate({"warmup": 8, "init": {"warmup": 6}})


def test_retired_keys_load_at_their_fixed_value_and_refuse_any_other():
    cfg = Outer.model_validate({"tie_ratio": 1.25, "margin": None})  # an old run's config.json stores every key
    assert "tie_ratio" not in cfg.model_dump()
    with pytest.raises(ValidationError, match=r"'tie_ratio' was retired: its setting is now fixed at 1.25 \(got 2.0\)"):
        Outer.model_validate({"tie_ratio": 2.0})
    with pytest.raises(ValidationError, match="'margin' was retired"):
        Outer.model_validate({"margin": 3})
    with pytest.raises(ValidationError, match="tie_ratioo"):  # an unknown key stays an error
        Outer.model_validate({"tie_ratioo": 1.25})
