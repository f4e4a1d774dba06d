"""A sequence being written lives in a temporary folder: SIGTERM removes it, and what a killed writer left is
removed by the next start."""
from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import time

import pytest

from pvslam_plugins.datasets.synthetic import generator

# stands in for the renderer: the first frame, then a long wait (the real one spends ~0.1-1 s per frame)
SLOW_WRITER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from pvslam_plugins.datasets.synthetic import writer

    def slow(sc, tmp, progress):
        (tmp / "rgb").mkdir(parents=True)
        (tmp / "rgb" / "000000.png").write_bytes(bytes(4096))
        print("writing", flush=True)
        time.sleep(120)

    writer._write_into = slow
    writer.write_sequence(None, Path(sys.argv[1]) / "seq")
""")


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_sigterm_while_writing_removes_the_temporary_folder(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", SLOW_WRITER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "writing"
        assert [p.name for p in tmp_path.iterdir()][0].startswith(".seq.tmp-")  # the folder being written
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == -signal.SIGTERM  # still ends as SIGTERM ends a process
    finally:
        proc.kill()
        proc.wait()
    assert list(tmp_path.iterdir()) == []  # neither the sequence nor its temporary folder


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_the_next_start_removes_what_a_killed_writer_left(tmp_path, monkeypatch):
    monkeypatch.setenv("PVSLAM_CACHE", str(tmp_path / "cache"))
    root = generator.cache_path("indoor_handheld", num_frames=3, width=48, height=32)
    root.parent.mkdir(parents=True)
    host = re.sub(r"[^A-Za-z0-9-]", "", socket.gethostname())[:40] or "host"

    def left(name: str, age_h: float = 0.0):
        d = root.parent / name
        (d / "rgb").mkdir(parents=True)
        (d / "rgb" / "000000.png").write_bytes(bytes(100))
        t = time.time() - age_h * 3600
        for p in (d / "rgb" / "000000.png", d / "rgb", d):
            os.utime(p, (t, t))
        return d

    killed = left(f".{root.name}.tmp-{host}-{_dead_pid()}-0123abcd")  # SIGKILLed writer of this host
    old = left(f".other-seq.tmp-{os.getppid()}-89abcdef", age_h=7)  # untouched for hours, pid alive or reused
    busy = left(f".busy-seq.tmp-{host}-{os.getppid()}-fedcba98")  # a live writer of this host: kept
    other_host = left(".busy-seq.tmp-elsewhere-1-aaaabbbb")  # another host's fresh writer: kept
    unrelated = left(".not-a-sequence")
    seq = generator.ensure_cached("indoor_handheld", num_frames=3, width=48, height=32, progress=False)
    assert generator.is_complete(seq)
    assert not killed.exists() and not old.exists()
    assert busy.exists() and other_host.exists() and unrelated.exists()
    # a complete cached sequence is reused, and the sweep runs on that start too
    again = left(f".{root.name}.tmp-{host}-{_dead_pid()}-33334444")
    assert generator.ensure_cached("indoor_handheld", num_frames=3, width=48, height=32, progress=False) == seq
    assert not again.exists()
