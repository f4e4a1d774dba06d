"""Atomic file replacement shared by the output writers.

Per-frame files (a panoptic PNG a frame, a depth file a keyframe, an export's images: thousands in a run) are
written with ``durable=False``: renamed into place whole but not flushed to the disk one by one (an fsync a frame
costs the output thread more than the PNG's encoding, and far more on a network or spinning disk); a crash of
pvslam still leaves each of them whole, a crash of the OS may lose the last seconds of them. The run's own record
(trajectories, checkpoints, metrics, the resolved config, point clouds) is fsynced before it replaces the old file.

Two details matter to users: ``tempfile.mkstemp`` creates files with mode 0600 whatever the umask, so the
temporary file is given the mode an ordinary ``open()`` would (``0666 & ~umask``) before it replaces the target;
and an OS error is re-raised naming the *target* file (a full disk reports no file name at all, and a failed
``os.replace`` names only the hidden temporary file).
"""
from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from typing import Iterator

_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux), else set-and-restore."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    with _UMASK_LOCK:  # os.umask can only be read by setting it; restore at once
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def _named(exc: OSError, path: str) -> OSError:
    """``exc`` as an OSError of the same errno (so the same subclass) whose file name is ``path``."""
    if exc.filename == path:
        return exc
    new = OSError(exc.errno, exc.strerror or str(exc), path) if exc.errno else OSError(f"{exc} (writing {path})")
    new.__cause__ = exc
    return new


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", durable: bool = True, **kwargs) -> Iterator:
    """Open a temporary file next to ``path``; on a clean exit fsync it (``durable``) and ``os.replace`` it onto
    ``path``.

    On an exception the temporary file is removed and ``path`` keeps its previous content; an ``OSError`` is
    re-raised with ``path`` as its file name.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    tmp = None
    try:
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp", dir=folder)
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(exc, OSError):
            raise _named(exc, path) from exc
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes, durable: bool = True) -> None:
    with atomic_open(path, "wb", durable) as f:
        f.write(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(text)
