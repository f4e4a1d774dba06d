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
