"""The command line: fast start (no heavy imports), config show/validate, plugins, exit codes."""
import json
import subprocess
import sys
from pathlib import Path

from pvslam_core.cli import main

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_help_imports_no_heavy_library():
    code = ("import sys, contextlib, io\n"
            "from pvslam_core.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    main([])\n"
            "heavy = [m for m in ('torch', 'cv2', 'evo', 'matplotlib', 'pydantic') if m in sys.modules]\n"
            "print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_help_lists_commands(capsys):
    main([])
    out = capsys.readouterr().out
    for cmd in ("run", "plugins", "config", "synth", "eval", "export"):
        assert cmd in out


def test_config_validate_ok_and_error(tmp_path, capsys):
    good = tmp_path / "good.toml"
    good.write_text('[loop]\nplugin = "none"\n')
    assert main(["config", "validate", str(good)]) == 0
    assert "OK" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text('[optimizer]\nplugin = "online_ba"\nwindw = 3\n')
    assert main(["config", "validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "optimizer.windw" in err and "window" in err


def test_config_show_applies_set(capsys):
    assert main(["config", "show", "--json", "--set", "run.seed=9", "--set", "loop.plugin=none"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["run"]["seed"] == 9 and data["loop"] == {"plugin": "none"}
    assert data["frontend"]["plugin"] == "flow" and len(data["frontend"]) > 3


def test_config_show_prints_a_toml_config_that_loads_back(capsys, tmp_path):
    """The default output is a TOML config file: run with it, the run gets the same resolved config."""
    from pvslam_core.config import load_config

    for cfg_args in ([], ["--config", str(CONFIGS / "kitti.toml")], ["--config", str(CONFIGS / "raft_gru.toml")]):
        assert main(["config", "show", *cfg_args, "--set", "run.seed=9", "--set", "outputs.ply_voxel=0.01"]) == 0
        text = capsys.readouterr().out
        assert text.startswith("# resolved config") and "\n[run]\nname = " in text and "seed = 9" in text
        path = tmp_path / "shown.toml"
        path.write_text(text)
        want = load_config(cfg_args[1] if cfg_args else None, ["run.seed=9", "outputs.ply_voxel=0.01"])
        assert load_config(path).to_dict() == want.to_dict()


PLANNED = """
[[plugin]]
name = "flow"
interface = "frontend"
entry_point = "pvslam_plugins.frontends.flow"
description = "DIS optical flow"
builtin = true

[[plugin]]
name = "future_loop"
interface = "loop"
entry_point = "someone_else.future_loop"
description = "a catalogued plugin that is not installed"
install = "pip install future-loop"
status = "planned"
[[plugin.weights]]
name = "future-loop-weights"
url = "https://example.org/w.pth"
"""


def test_plugins_json(capsys, tmp_path, monkeypatch):
    (tmp_path / "registry.toml").write_text(PLANNED)
    monkeypatch.setenv("PVSLAM_REGISTRY", str(tmp_path / "registry.toml"))
    assert main(["plugins", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    by = {(r["interface"], r["name"]): r for r in rows}
    assert by[("frontend", "flow")]["state"] == "installed"
    assert by[("dataset", "npz")]["state"] == "installed" and by[("dataset", "npz")]["distribution"] == "pvslam-npz"
    assert by[("loop", "future_loop")]["state"] == "planned" and by[("loop", "future_loop")]["needs_weights"]


def test_unknown_plugin_exit_code(capsys):
    assert main(["config", "show", "--set", "frontend.plugin=droidd"]) == 2
    err = capsys.readouterr().err
    assert "droidd" in err and "flow" in err


def test_one_openmp_thread_unless_the_user_chose(tmp_path):
    """The command line sets OMP_NUM_THREADS=1 before torch loads (OpenMP teams are per thread: the reader, output
    and flow threads' own teams spun against the pipeline), and keeps a value the user set."""
    import os
    import subprocess

    probe = ("import os; from pvslam_core.cli import main; main(['plugins', '--json']); import torch; "
             "print('OMP', os.environ['OMP_NUM_THREADS'], torch.get_num_threads())")
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True).stdout
    assert "OMP 1 1" in out
    out = subprocess.run([sys.executable, "-c", probe], env={**env, "OMP_NUM_THREADS": "2"}, capture_output=True,
                         text=True, check=True).stdout
    assert "OMP 2 2" in out


def test_synth_writes_a_sequence_through_another_lens(tmp_path, capsys):
    out = tmp_path / "wide"
    assert main(["synth", "--scenario", "indoor_handheld", "--frames", "2", "--width", "48", "--height", "32",
                 "--hfov", "90", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip().endswith(str(out))
    assert (out / "calib.txt").read_text().split()[:2] == ["24.000000", "24.000000"]  # 48 px wide at 90 deg
    assert json.loads((out / "meta.json").read_text())["hfov_deg"] == 90.0
