"""A store for per-keyframe and per-frame arrays that the map needs again only later (the final BA's retired edge
observations, the frames' correspondences for their final motion-only BA), kept on disk instead of in memory.

:class:`SpillStore` keeps tensors under a small integer handle.  With a directory, each :meth:`~SpillStore.put`
appends the tensors' raw bytes to one anonymous temporary file in that directory (unlinked at once: nothing is left
behind, even when the process is killed) and only their offset, shape, dtype and device stay in memory;
:meth:`~SpillStore.get` reads them back bit for bit.  Without a directory the tensors are kept as they are (the
same objects, no copy).  The file's pages live in the OS page cache, not in the process's memory; its disk space
grows with the run (about the size of what would otherwise be held in memory) and is freed when the store closes.
"""
from __future__ import annotations

import os
import tempfile
import threading
from pathlib import Path
from typing import Optional

import torch

_Meta = tuple[int, int, tuple, torch.dtype, torch.device]  # offset, bytes, shape, dtype, device


class SpillStore:
    """Tensors by handle, in memory or spilled to an unlinked file under ``directory`` (see the module docstring)."""

    def __init__(self, directory: Optional[Path | str] = None) -> None:
        self._file = None
        if directory is not None:
            Path(directory).mkdir(parents=True, exist_ok=True)
            self._file = tempfile.TemporaryFile(dir=directory, prefix=".pvslam-spill-")
        self._lock = threading.Lock()
        self._end = 0  # bytes written to the file so far
        self._next = 0
        self._items: dict[int, tuple] = {}  # handle -> tensors (in memory) or their _Meta (on disk)

    @property
    def on_disk(self) -> bool:
        return self._file is not None

    def __len__(self) -> int:
        return len(self._items)

    def put(self, *tensors: torch.Tensor) -> int:
        """Keep ``tensors``; returns their handle."""
        with self._lock:
            if self._file is None:
                item = tuple(tensors)
            else:
                item = tuple(self._write(t) for t in tensors)
            handle, self._next = self._next, self._next + 1
            self._items[handle] = item
            return handle

    def get(self, handle: int) -> tuple[torch.Tensor, ...]:
        """The tensors kept under ``handle`` (read back from disk: new tensors with the same bits, dtype, shape and
        device)."""
        with self._lock:
            item = self._items[handle]
            if self._file is None:
                return item
            return tuple(self._read(meta) for meta in item)

    def drop(self, handle: Optional[int]) -> None:
        """Forget ``handle`` (None: nothing); on disk its bytes stay in the file until the store closes."""
        if handle is not None:
            with self._lock:
                self._items.pop(handle, None)

    def close(self) -> None:
        """Forget everything and free the file."""
        with self._lock:
            self._items.clear()
            if self._file is not None:
                self._file.close()

    def _write(self, t: torch.Tensor) -> _Meta:
        data = t.detach().to("cpu").contiguous().reshape(-1).view(torch.uint8).numpy().tobytes()
        os.pwrite(self._file.fileno(), data, self._end)
        meta = (self._end, len(data), tuple(t.shape), t.dtype, t.device)
        self._end += len(data)
        return meta

    def _read(self, meta: _Meta) -> torch.Tensor:
        offset, size, shape, dtype, device = meta
        data = os.pread(self._file.fileno(), size, offset)
        if len(data) != size:
            raise OSError(f"spill file: read {len(data)} of {size} bytes at offset {offset}")
        t = torch.frombuffer(bytearray(data), dtype=torch.uint8) if size else torch.zeros(0, dtype=torch.uint8)
        return t.view(dtype).reshape(shape).to(device)
