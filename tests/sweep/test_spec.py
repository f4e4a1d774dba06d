"""The sweep file: validation errors (file + key path), grid expansion, seeds, stable and safe cell names."""
from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from pvslam_core.config import ConfigError
from pvslam_core.sweep.spec import cell_name, config_key, load_sweep, sanitise

from sweep_helpers import sweep_text


def _write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_grid_expansion_and_seed_semantics(tmp_path):
    seq = textwrap.dedent('''
        [[sequence]]
        name = "own"
        seeds = [7]
        dataset = { plugin = "synthetic", scenario = "indoor_handheld", num_frames = 20, seed = 3 }
        ''')
    plan = load_sweep(_write(tmp_path, sweep_text(tmp_path / "out", scenarios=("driving_loop", "moving_vehicles"),
                                                  seeds=(0, 1), extra_sequences=seq)))
    assert plan.sequences == ["driving_loop", "moving_vehicles", "own"]
    assert plan.variants == ["online_ba+loop", "offline_ba"]
    assert len(plan.cells) == (2 * 2 + 1) * 2
    by = {(c.sequence, c.seed, c.variant): c for c in plan.cells}
    c = by[("moving_vehicles", 1, "offline_ba")].config.pipeline
    # a scenario's seed is both the generated scene's and the run's; the variant's deltas apply on top
    assert c.dataset.params["seed"] == 1 and c.run.seed == 1 and c.dataset.params["num_frames"] == 36
    assert c.optimizer.plugin == "offline_ba" and c.loop.plugin == "none" and c.segmenter.plugin == "labels"
    o = by[("own", 7, "online_ba+loop")].config.pipeline
    assert o.dataset.params["seed"] == 3 and o.run.seed == 7  # a dataset section is used as written
    assert plan.directory == tmp_path / "out" / "tiny"


@pytest.mark.parametrize("text,needles", [
    ('[sweep]\nscenaros = ["driving_loop"]\n[[variant]]\nname = "a"\n', ["unknown key 'sweep.scenaros'", "scenarios"]),
    ('[sweep]\nscenarios = ["driving_lop"]\n[[variant]]\nname = "a"\n', ["sweep.scenarios", "driving_lop", "driving_loop"]),
    ('[sweep]\nseeds = []\nscenarios = ["driving_loop"]\n[[variant]]\nname = "a"\n', ["sweep.seeds"]),
    ('[sweep]\nscenarios = ["driving_loop"]\n', ["[[variant]]"]),
    ('[sweep]\n[[variant]]\nname = "a"\n', ["no sequences"]),
    ('[sweep]\nscenarios = ["driving_loop"]\n[dataset]\nplugin = "kitti"\n[[variant]]\nname = "a"\n', ["[[sequence]]"]),
    ('[sweep]\nscenarios = ["driving_loop"]\n[[variant]]\nname = "a"\n[[variant]]\nname = "a"\n', ["duplicate variant"]),
    ('[sweep]\nscenarios = ["driving_loop"]\n[[variant]]\nname = "a"\n"dataset.seed" = 3\n', ["cannot change the dataset"]),
    ('[sweep]\n[[sequence]]\nname = "k"\ndataset = { root = "x" }\n[[variant]]\nname = "a"\n',
     ["sequence.0.dataset", "plugin"]),
    ('[sweep]\nscenarios = ["driving_loop"]\n[[variant]]\nname = "a"\n"optimizer.windw" = 3\n',
     ["variant 'a'", "optimizer.windw", "window"]),
])
def test_errors_name_file_and_key(tmp_path, text, needles):
    p = _write(tmp_path, text, "bad_sweep.toml")
    with pytest.raises(ConfigError) as ei:
        load_sweep(p)
    msg = str(ei.value)
    assert "bad_sweep.toml" in msg
    for n in needles:
        assert n in msg, (n, msg)


@pytest.mark.parametrize("raw", ["../../etc", "..", ".", "/abs/path", "a/b", "a\\b", "", "é ü", "x" * 300, "-.-"])
def test_sanitised_names_stay_one_plain_folder(tmp_path, raw):
    name = cell_name(raw, 0, raw)
    assert name and "/" not in name and "\\" not in name and not name.startswith(".") and len(name) < 160
    root = tmp_path / "cells"
    assert (root / name).resolve().parent == root.resolve()
    assert sanitise(raw) not in ("", ".", "..")


def test_names_stable_readable_and_distinct():
    assert cell_name("driving_loop", 1, "online_ba+loop") == "driving_loop__seed1__online_ba+loop"
    assert cell_name("a/b", 0, "v") != cell_name("a_b", 0, "v")  # sanitising never merges two cells
    assert cell_name("a/b", 0, "v") == cell_name("a/b", 0, "v")  # stable across invocations (resume)


def test_key_ignores_run_only_settings(tmp_path):
    p = _write(tmp_path, sweep_text(tmp_path / "out"))
    a = load_sweep(p).cells[0]
    b = load_sweep(p, overrides=["run.threads=7", "run.progress=false"]).cells[0]
    c = load_sweep(p, overrides=["graph.init.warmup=4"]).cells[0]
    assert a.key == b.key and a.key != c.key and a.key == config_key(a.config)


def test_set_overrides_reach_sweep_and_base_not_the_grid(tmp_path):
    p = _write(tmp_path, sweep_text(tmp_path / "out", seeds=(0, 1)))
    plan = load_sweep(p, overrides=["sweep.seeds=[5]", "graph.init.warmup=4"])
    assert {c.seed for c in plan.cells} == {5} and all(c.config.pipeline.graph.init.warmup == 4 for c in plan.cells)
    with pytest.raises(ConfigError, match=r"--set dataset.num_frames.*scenario_params"):
        load_sweep(p, overrides=["dataset.num_frames=10"])
