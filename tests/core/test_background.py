"""Work beside the pipeline thread (pvslam_core.background) and the panoptic journal: reading ahead yields the same
frames in order with bounded look-ahead and errors at the right frame; writing behind keeps the run's files
identical to writing in place; a run killed before segments.json keeps every written frame in the journal."""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from pvslam_core.api import run_config
from pvslam_core.background import BackgroundWriter, read_ahead, with_next
from pvslam_core.outputs.panoptic_png import JOURNAL, PanopticWriter, load_panoptic_dir, read_segments_json
from pvslam_core.types import PanopticSegmentation, Segment


def _threads(prefix: str) -> int:
    return sum(t.name.startswith(prefix) for t in threading.enumerate())


def test_read_ahead_same_items_bounded_lookahead():
    produced = []

    def items():
        for i in range(20):
            produced.append(i)
            yield i

    got = []
    for x in read_ahead(items(), depth=3, name="t-read"):
        time.sleep(0.002)  # a slow consumer: the producer must wait, not run to the end
        assert len(produced) - len(got) <= 3 + 2  # queue (3) + one being put + the one handed out
        got.append(x)
    assert got == list(range(20))
    assert list(read_ahead(iter(range(5)), depth=0)) == [0, 1, 2, 3, 4]  # depth 0: no thread


def test_read_ahead_error_at_its_item_and_stop_on_close():
    def failing():
        yield 1
        yield 2
        raise ValueError("frame 3 is corrupt")

    got = []
    with pytest.raises(ValueError, match="frame 3 is corrupt"):
        for x in read_ahead(failing(), depth=2, name="t-fail"):
            got.append(x)
    assert got == [1, 2]
    gen = read_ahead(iter(range(10**6)), depth=2, name="t-close")
    assert next(gen) == 0
    gen.close()  # a loop left early (break, Ctrl-C): the reader thread ends
    time.sleep(0.3)
    assert _threads("t-close") == 0


def test_with_next_pairs_each_item_with_the_next_and_reads_ahead_only_when_asked():
    pulled = []

    def items(n, fail_at=None):
        for i in range(n):
            if i == fail_at:
                raise ValueError(f"item {i} is corrupt")
            pulled.append(i)
            yield i

    got = []
    for x, nxt in with_next(items(4), ahead=True):
        assert pulled[-1] == (x + 1 if x < 3 else 3)  # the next item was read before this one is handed out
        got.append((x, nxt))
    assert got == [(0, 1), (1, 2), (2, 3), (3, None)]
    pulled.clear()
    got = []
    for x, nxt in with_next(items(3), ahead=False):
        assert pulled[-1] == x  # nothing read beyond the item handed out (a live source's next frame may not exist)
        got.append((x, nxt))
    assert got == [(0, None), (1, None), (2, None)]
    got = []
    with pytest.raises(ValueError, match="item 2 is corrupt"):
        for x, nxt in with_next(items(5, fail_at=2), ahead=True):
            got.append((x, nxt))
    assert got == [(0, 1), (1, None)]  # the item before the failing one is still handed out
    assert list(with_next([], ahead=True)) == []


def test_background_writer_order_and_errors():
    out = []
    w = BackgroundWriter(depth=2, name="t-writer")
    for i in range(50):
        w.submit(out.append, i)
    w.drain()
    assert out == list(range(50))

    def boom(_):
        raise OSError("disk full")

    w.submit(boom, 0)
    w.submit(out.append, 99)  # may run or be skipped: the error is what matters
    with pytest.raises(OSError, match="disk full"):
        w.drain()
    w.submit(out.append, 100)  # the writer goes on after the error was handed over
    w.close()
    w.close()  # idempotent
    assert out[-1] == 100 and _threads("t-writer") == 0
    with pytest.raises(RuntimeError):
        w.submit(out.append, 1)


def _seg(t: int) -> PanopticSegmentation:
    ids = torch.full((6, 8), 1000, dtype=torch.int64)
    ids[1:4, t % 5: t % 5 + 3] = 2000 + t
    return PanopticSegmentation(ids, [Segment(1000, 1, False, 0.5), Segment(2000 + t, 2, True, 0.25 + t / 100)])


def test_journal_keeps_every_frame_of_a_killed_run(tmp_path):
    w = PanopticWriter(tmp_path, categories=[{"id": 1, "name": "road", "isthing": 0}], flush_every=0, journal=True)
    for t in range(7):
        w.write(t, _seg(t))
    # killed here: no close(), no segments.json; a half-written last line as a crash can leave
    with open(tmp_path / "panoptic" / JOURNAL, "a", encoding="utf-8") as f:
        f.write('{"image": {"id": 7, "file_na')
    assert not (tmp_path / "panoptic" / "segments.json").exists()
    meta = read_segments_json(tmp_path / "panoptic")
    assert [a["frame_index"] for a in meta["annotations"]] == list(range(7))
    assert {c["id"] for c in meta["categories"]} == {1, 2}  # the declared one and the one only seen
    loaded = load_panoptic_dir(tmp_path / "panoptic")
    for t in range(7):
        np.testing.assert_array_equal(loaded[t].ids.numpy(), _seg(t).ids.numpy())
        assert loaded[t].segment(2000 + t).score == pytest.approx(0.25 + t / 100)
    # a clean close writes segments.json (the same content) and removes the journal
    expected = w.to_json()
    w.close()
    assert not (tmp_path / "panoptic" / JOURNAL).exists()
    assert json.loads((tmp_path / "panoptic" / "segments.json").read_text()) == json.loads(json.dumps(expected))


def _files(run_dir: Path) -> dict[str, bytes]:
    keep = ("panoptic/", "trajectory.txt", "keyframes.txt", "loops.json")
    return {str(p.relative_to(run_dir)): p.read_bytes() for p in sorted(run_dir.rglob("*"))
            if p.is_file() and str(p.relative_to(run_dir)).startswith(keep)}


def test_writing_behind_gives_the_same_files(tmp_path, fake_registry, fake_config_file):
    runs = {}
    for depth in (0, 3):
        res = run_config(fake_config_file, registry=fake_registry,
                         overrides=[f"run.write_behind={depth}", f'run.name="wb{depth}"', "evaluation.enabled=false"])
        runs[depth] = _files(Path(res.run_dir))
    assert runs[0].keys() == runs[3].keys() and len([k for k in runs[0] if k.endswith(".png")]) == 12
    for name in runs[0]:
        assert runs[0][name] == runs[3][name], name
    assert _threads("pvslam-output") == 0
