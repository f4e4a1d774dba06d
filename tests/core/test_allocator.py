"""pvslam_core/allocator.py: freed scratch memory stays in the process (no page faults on the next call)."""
import subprocess
import sys

import pytest

from pvslam_core import allocator

PROBE = r"""
import resource, sys
import numpy as np
if sys.argv[1] == "1":
    from pvslam_core.allocator import keep_freed_memory
    assert keep_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = np.ones(40 << 17); del a  # 40 MB: above glibc's largest dynamic mmap threshold (32 MB)
f0 = faults()
for _ in range(5):  # what a BA call does with its per-chunk scratch
    a = np.ones(40 << 17); del a
print(faults() - f0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_scratch_memory_is_reused_instead_of_faulted_in_again():
    def faults(tuned: bool) -> int:
        out = subprocess.run([sys.executable, "-c", PROBE, "1" if tuned else "0"], capture_output=True, text=True,
                             check=True)
        return int(out.stdout.strip())

    # the default: every allocation maps fresh pages (2660 faults here; >= 80 even if all were 2 MB huge pages)
    assert faults(False) >= 80
    assert faults(True) <= 10  # the freed block is reused (0 here)


def test_set_once_and_the_pipeline_asks_for_it(monkeypatch):
    if sys.platform.startswith("linux"):
        assert allocator.keep_freed_memory() is True and allocator.keep_freed_memory() is True
    from pvslam_core.config import validate_pipeline

    assert validate_pipeline({}).run.keep_freed_memory is True
    with pytest.raises(Exception, match="keep_freed_memoryy"):
        validate_pipeline({"run": {"keep_freed_memoryy": False}})


RELEASE_PROBE = r"""
import numpy as np
from pvslam_core.allocator import keep_freed_memory, release_freed_memory
assert keep_freed_memory()
def rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20
blocks = [np.ones(1 << 17) for _ in range(300)]  # 300 x 1 MB in the heap (below the raised mmap threshold)
pin = np.ones(1 << 17)  # a live block above them keeps the heap's top from being trimmed
del blocks
before = rss_mb()
released = release_freed_memory()
print(before - rss_mb(), released)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_freed_pages_inside_the_heap_go_back_to_the_os():
    out = subprocess.run([sys.executable, "-c", RELEASE_PROBE], capture_output=True, text=True, check=True)
    dropped_mb, released = out.stdout.split()
    assert released == "True"
    assert float(dropped_mb) >= 250  # the 300 MB freed below the live block (kept without the release)


def test_the_pipeline_releases_every_few_frames(monkeypatch, tmp_path):
    from pvslam_core import pipeline as pipeline_module
    from pvslam_core.api import run_config

    calls = []
    monkeypatch.setattr(pipeline_module, "RELEASE_EVERY", 3)
    monkeypatch.setattr(pipeline_module, "release_freed_memory", lambda: calls.append(1) or True)
    run_config(None, overrides=[f'run.output_dir="{tmp_path.as_posix()}"', "run.progress=false", "run.max_frames=7",
                                "outputs.ply=false", "outputs.plots=false"])
    assert len(calls) == 2  # after frames 3 and 6 of 7
