"""The final map's files come from one table (``pvslam_core/outputs/formats.py``: ``MAP_WRITERS``): a new format is a
writer function plus its line there, and a failing writer is a named write error like every other file."""
import json
from pathlib import Path

import pytest

from pvslam_core.api import run_config
from pvslam_core.outputs import formats
from pvslam_core.run_outputs import OutputWriteError


def keyframe_list(run):
    """A toy format: the keyframes' input-frame indices and timestamps, one per line."""
    kf = run.keyframes
    path = Path(run.dir) / "keyframe_list.txt"
    path.write_text("".join(f"{int(i)} {float(t):.6f}\n" for i, t in zip(kf.frame_index.tolist(), kf.timestamps)))
    return {"keyframes": len(kf.ids)}


def broken(run):
    raise OSError(28, "No space left on device", str(Path(run.dir) / "broken.bin"))


def test_a_new_format_is_one_line_in_the_table(monkeypatch, fake_registry, fake_config_file):
    line = formats.MapWriter("keyframe_list.txt", f"{__name__}:keyframe_list", "keyframe_depth", "keyframe list")
    monkeypatch.setattr(formats, "MAP_WRITERS", (*formats.MAP_WRITERS, line))
    res = run_config(fake_config_file, registry=fake_registry)
    run = Path(res.run_dir)
    rows = (run / "keyframe_list.txt").read_text().splitlines()
    kf = json.loads((run / "keyframes" / "keyframes.json").read_text())["keyframes"]
    assert len(rows) == len(kf) > 1
    assert [int(r.split()[0]) for r in rows] == [k["frame_index"] for k in kf]
    # its switch is one of [outputs]: off, nothing written
    res = run_config(fake_config_file, registry=fake_registry, overrides=["outputs.keyframe_depth=false"])
    assert not (Path(res.run_dir) / "keyframe_list.txt").exists()


def test_a_failing_writer_is_a_named_write_error(monkeypatch, fake_registry, fake_config_file):
    line = formats.MapWriter("broken.bin", f"{__name__}:broken", "keyframe_depth", "always fails")
    monkeypatch.setattr(formats, "MAP_WRITERS", (line, *formats.MAP_WRITERS))
    with pytest.raises(OutputWriteError, match="broken.bin: No space left on device"):
        run_config(fake_config_file, registry=fake_registry)
