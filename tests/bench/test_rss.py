"""bench.rss: a child's peak memory is its own, not its launcher's."""
import json
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.rss import current_rss_mb, peak_rss_mb  # noqa: E402

CHILD = ("import json, resource, sys; sys.path.insert(0, sys.argv[1]); from bench.rss import peak_rss_mb; "
         "print(json.dumps([peak_rss_mb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024]))")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc (Linux)")
def test_child_peak_is_not_the_launchers():
    held = np.ones(300 * 2**20 // 8)  # 300 MiB resident in this process when the child starts
    out = subprocess.run([sys.executable, "-c", CHILD, str(ROOT)], capture_output=True, text=True, check=True)
    own, inherited = json.loads(out.stdout)
    assert held.sum() > 0
    assert inherited >= 300  # what ru_maxrss says in a child of a large process
    assert own < 200  # a bare interpreter with numpy


def test_reads_vmhwm_and_falls_back(tmp_path):
    status = tmp_path / "status"
    status.write_text("Name:\tpython\nVmPeak:\t 9999999 kB\nVmHWM:\t  524288 kB\nVmRSS:\t  100 kB\n")
    assert peak_rss_mb(status) == 512.0
    status.write_text("Name:\tpython\n")
    assert peak_rss_mb(status) > 0  # no VmHWM line: this process's ru_maxrss
    assert peak_rss_mb(tmp_path / "missing") > 0


def test_current_rss(tmp_path):
    statm = tmp_path / "statm"
    statm.write_text("1000 256 10 1 0 100 0\n")  # pages: size, resident, ...
    assert current_rss_mb(statm) == 256 * resource.getpagesize() / 2**20
    assert current_rss_mb(tmp_path / "missing") is None
