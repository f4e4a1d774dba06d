"""Peak resident memory of this process alone.

``getrusage(RUSAGE_SELF).ru_maxrss`` is not that in a child process: Linux carries the high-water mark over fork and
exec, so a child launched by a process holding 1 GB reports at least 1 GB however little it uses.  The kernel's
``VmHWM`` (``/proc/self/status``) belongs to the address space, which exec replaces, so it is the child's own peak.
Where there is no ``/proc`` (macOS) ``ru_maxrss`` is the fallback, with that caveat.
"""
from __future__ import annotations

import re
import resource
import sys
from pathlib import Path

__all__ = ["current_rss_mb", "peak_rss_mb"]


def current_rss_mb(statm: Path = Path("/proc/self/statm")) -> float | None:
    """This process's resident set size now (MiB), or None where there is no ``/proc``."""
    try:
        return int(statm.read_text().split()[1]) * resource.getpagesize() / 2**20
    except (OSError, IndexError, ValueError):
        return None


def peak_rss_mb(status: Path = Path("/proc/self/status")) -> float:
    """This process's peak resident set size (MiB) since its last exec."""
    try:
        m = re.search(r"^VmHWM:\s+(\d+)\s+kB", status.read_text(), re.MULTILINE)
    except OSError:
        m = None
    if m is not None:
        return int(m.group(1)) / 1024.0
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 1024.0  # bytes on macOS, KiB on Linux
