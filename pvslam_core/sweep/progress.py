"""The grid's progress display on stderr: cells done / running / failed, elapsed, estimated remaining.

On a terminal one status line is redrawn in place; otherwise (CI logs, a redirected stderr) one line is printed
per finished cell, so a log still shows the whole history.
"""
from __future__ import annotations

import sys
import time
from typing import Optional, TextIO


def _hms(seconds: Optional[float]) -> str:
    if seconds is None:
        return "?"
    s = int(round(max(0.0, seconds)))
    return f"{s // 3600}:{(s // 60) % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class GridProgress:
    def __init__(self, total: int, skipped: int, slots: int, stream: Optional[TextIO] = None,
                 enabled: bool = True, label: str = "sweep"):
        self.total, self.skipped, self.slots = total, skipped, max(1, slots)
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.label = label
        self.tty = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.t0 = time.perf_counter()
        self.running: dict[str, float] = {}  # cell -> start time
        self.done = self.failed = 0
        self.durations: list[float] = []
        self.phase = ""
        self._last_draw = 0.0

    # ------------------------------------------------------------------------------------------ events --
    def set_phase(self, text: str) -> None:
        self.phase = text
        self.draw(force=True)

    def start(self, name: str) -> None:
        self.running[name] = time.perf_counter()
        self.draw()

    def finish(self, name: str, status: str, error: str = "") -> None:
        started = self.running.pop(name, None)
        if started is not None:
            self.durations.append(time.perf_counter() - started)
        if status == "done":
            self.done += 1
        else:
            self.failed += 1
        if self.enabled and not self.tty:
            extra = f": {error}" if error else ""
            print(f"[{self.label}] {status:<6} {name}{extra}  ({self.line()})", file=self.stream, flush=True)
        self.draw(force=True)

    # ------------------------------------------------------------------------------------------ output --
    def eta(self) -> Optional[float]:
        """Remaining cells x mean cell time / runs at a time, minus what the running cells have done already."""
        if not self.durations:
            return None
        mean = sum(self.durations) / len(self.durations)
        left = self.total - self.skipped - self.done - self.failed
        now = time.perf_counter()
        in_flight = sum(min(now - t, mean) for t in self.running.values())
        return max(0.0, (left * mean - in_flight) / min(self.slots, max(1, left)))

    def line(self) -> str:
        finished = self.skipped + self.done + self.failed
        parts = [f"{finished}/{self.total} cells", f"{self.done} done", f"{len(self.running)} running",
                 f"{self.failed} failed"]
        if self.skipped:
            parts.append(f"{self.skipped} already finished")
        parts.append(f"elapsed {_hms(time.perf_counter() - self.t0)}")
        parts.append(f"remaining ~{_hms(self.eta())}")
        return ", ".join(parts)

    def draw(self, force: bool = False) -> None:
        if not self.tty:
            return
        now = time.perf_counter()
        if not force and now - self._last_draw < 0.5:
            return
        self._last_draw = now
        text = f"[{self.label}] {self.phase + ': ' if self.phase else ''}{self.line()}"
        self.stream.write("\r\033[K" + text)
        self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\r\033[K")
        if self.enabled:
            print(f"[{self.label}] {self.line()}", file=self.stream, flush=True)
