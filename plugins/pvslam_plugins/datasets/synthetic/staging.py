"""The temporary folder a sequence is written into before it is renamed onto its final name.

A sequence folder is complete or absent: :func:`.writer.write_sequence` writes into a hidden sibling
``.<name>.tmp-<host>-<pid>-<random>`` and renames it at the end.  An exception or Ctrl-C removes the temporary
folder; so does SIGTERM (:func:`sigterm_cleans_up`: the process still ends as SIGTERM ends it).  What no handler
can clean (SIGKILL, a power cut) is removed by the next writer into the same folder (:func:`sweep_stale`): a
temporary folder whose process is gone on this host, or that nobody wrote into for :data:`STALE_HOURS`.
"""
from __future__ import annotations

import logging
import os
import re
import shutil
import signal
import socket
import sys
import threading
import time
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

LOG = logging.getLogger("pvslam")

#: a temporary folder nobody wrote into for this long is removed whoever made it (its writer's process id may have
#: been reused, or it came from another host sharing the cache); a writer adds a frame every few hundred ms
STALE_HOURS = 6.0
_TEMP = re.compile(r"^\..+\.tmp-(?:(?P<host>[A-Za-z0-9-]+)-)?(?P<pid>\d+)-[0-9a-f]{8}$")


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9-]", "", socket.gethostname())[:40] or "host"


def temp_folder(root: Path) -> Path:
    """A new temporary sibling of ``root`` (not created here), named after this host and process."""
    return root.parent / f".{root.name}.tmp-{_host()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


def _alive(pid: int) -> bool:
    if sys.platform == "win32":  # os.kill would terminate it there: unknown, let the age decide
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process (PermissionError): it exists
        return True
    return True


def _last_write(path: Path) -> float:
    """The newest modification time of the folder and its direct entries (frames go into rgb/, depth/, ...)."""
    newest = path.stat().st_mtime
    with os.scandir(path) as it:
        for entry in it:
            try:
                newest = max(newest, entry.stat(follow_symlinks=False).st_mtime)
            except OSError:
                continue
    return newest


def is_stale(path: Path, now: Optional[float] = None) -> bool:
    """Whether ``path`` is a temporary sequence folder whose writer is gone (see the module docstring)."""
    m = _TEMP.match(path.name)
    if m is None or path.is_symlink() or not path.is_dir():
        return False
    pid = int(m.group("pid"))
    if m.group("host") == _host() and pid != os.getpid() and not _alive(pid):
        return True
    try:
        return (now if now is not None else time.time()) - _last_write(path) > STALE_HOURS * 3600
    except OSError:  # removed meanwhile by its writer or another sweep
        return False


def sweep_stale(parent: Path) -> list[Path]:
    """Remove the stale temporary sequence folders in ``parent``; returns what was removed."""
    try:
        with os.scandir(parent) as it:
            entries = [Path(e.path) for e in it if _TEMP.match(e.name)]
    except OSError:  # no such folder yet
        return []
    removed = [p for p in entries if is_stale(p)]
    for p in removed:
        shutil.rmtree(p, ignore_errors=True)
    if removed:
        LOG.info("removed %d unfinished synthetic sequence folder(s) left by a stopped writer in %s: %s",
                 len(removed), parent, ", ".join(p.name for p in removed))
    return removed


class _Terminated(BaseException):
    """SIGTERM arrived while a sequence was written (a BaseException: no ``except Exception`` swallows it)."""


@contextmanager
def sigterm_cleans_up() -> Iterator[None]:
    """Within the block SIGTERM raises, so the writer's ``except`` removes its temporary folder; the process then
    ends by SIGTERM as it would have.  Only in the main thread and where SIGTERM has its default action: a handler
    someone installed (the pipeline's, which raises) is left alone."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        raise _Terminated()

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    except _Terminated:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)  # end as the default action would (exit status: killed by SIGTERM)
        raise
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
