"""glibc's allocator, told to keep freed memory for reuse (Linux only).

The dense BA and the VPS warp allocate per-call scratch tensors of a few MB (per-pixel Jacobians of a chunk of
edges).  glibc serves an allocation above ``M_MMAP_THRESHOLD`` (128 kB, raised dynamically to at most 32 MB) with a
fresh ``mmap`` and gives it back on ``free``, and trims the heap top above ``M_TRIM_THRESHOLD``; the next call then
page-faults the same memory in again and the kernel zero-fills it, a sizeable share of the process CPU for the same
results and peak memory (docs/decisions.md: run.keep_freed_memory).  With the thresholds at 64 MB / 256 MB the
scratch stays in the heap between calls.  ``GLIBC_TUNABLES=glibc.malloc.mmap_threshold=...`` does the same from the shell, but only
at process start, which a library cannot choose.

What stays also scatters: scratch blocks of changing sizes leave free pages inside the heap that the trim threshold
never returns (only the heap's top is trimmed), so a run's memory would creep up with the frames driven.
:func:`release_freed_memory` gives them back every :data:`RELEASE_EVERY` frames (the pipeline calls it).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import sys

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers (malloc.h)
M_MMAP_THRESHOLD = -3

# frames between two releases of the heap's free pages: a release costs a few ms and the next BA call faults its
# scratch in once more, so every 100 frames costs nothing measurable and keeps an endless run's memory from creeping
# (docs/decisions.md: RELEASE_EVERY)
RELEASE_EVERY = 100

_done: bool | None = None
_trim = None  # glibc's malloc_trim, once looked up; False where there is none


def _glibc(name: str, argtypes: list):
    """glibc's function ``name`` (returning int) with ``argtypes``, or None: not Linux, or a libc without it (musl
    has neither mallopt nor malloc_trim)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = argtypes, ctypes.c_int
    return fn


def keep_freed_memory(mmap_threshold: int = 64 << 20, trim_threshold: int = 256 << 20) -> bool:
    """Raise glibc's mmap and trim thresholds once per process; True when glibc accepted them (False elsewhere:
    another libc, macOS, Windows - nothing changes there)."""
    global _done
    if _done is not None:
        return _done
    mallopt = _glibc("mallopt", [ctypes.c_int, ctypes.c_int])
    _done = mallopt is not None and bool(mallopt(M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(
        mallopt(M_TRIM_THRESHOLD, int(trim_threshold)))
    return _done


def release_freed_memory() -> bool:
    """Return the free pages inside glibc's heaps (every arena, not only their tops) to the OS: ``malloc_trim(0)``.
    True where glibc released some; False where nothing was released or there is no glibc."""
    global _trim
    if _trim is None:
        _trim = _glibc("malloc_trim", [ctypes.c_size_t]) or False
    return bool(_trim(0)) if _trim else False
