"""Reading the simple one-line calibration format ``fx fy cx cy [k1 k2 p1 p2 [k3]]``.

Values are separated by whitespace and/or commas; lines starting with ``#`` and blank lines are ignored.  The
image size is not part of the file: the caller supplies it (usually from the first image).
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Sequence

from ..types import Intrinsics
from .base import DatasetError

_SPLIT = re.compile(r"[\s,]+")
VALID_COUNTS = (4, 8, 9)
VALUE_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def intrinsics_from_values(values: Sequence[float], width: int, height: int, source: str = "calib") -> Intrinsics:
    """``[fx, fy, cx, cy, (k1, k2, p1, p2, (k3))]`` -> :class:`Intrinsics`; errors name ``source``."""
    vals = [float(v) for v in values]
    if len(vals) not in VALID_COUNTS:
        raise DatasetError(
            f"{source}: expected 4, 8 or 9 calibration values (fx fy cx cy [k1 k2 p1 p2 [k3]]), found {len(vals)}"
        )
    try:
        return Intrinsics(vals[0], vals[1], vals[2], vals[3], int(width), int(height), tuple(vals[4:]))
    except ValueError as exc:
        raise DatasetError(f"{source}: invalid calibration: {exc}") from exc


def read_calibration_values(path: str | Path) -> list[float]:
    """The numbers of a calibration file (all non-comment lines together)."""
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: calibration file not found")
    vals: list[float] = []
    for lineno, line in enumerate(p.read_text().splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        for tok in _SPLIT.split(s):
            if not tok:
                continue
            try:
                v = float(tok)
            except ValueError:
                raise DatasetError(f"{p}:{lineno}: not a number: {tok!r}") from None
            if not math.isfinite(v):  # float() accepts 'inf' and 'nan'; the pipeline would fail much later
                raise DatasetError(f"{p}:{lineno}: {_value_name(len(vals))}={v} is not a finite number")
            vals.append(v)
    return vals


def _value_name(k: int) -> str:
    return VALUE_NAMES[k] if k < len(VALUE_NAMES) else f"value {k + 1}"


def read_calibration(path: str | Path, width: int, height: int) -> Intrinsics:
    """Read ``fx fy cx cy [k1 k2 p1 p2 [k3]]`` from ``path`` for an image of ``width`` x ``height`` pixels."""
    return intrinsics_from_values(read_calibration_values(path), width, height, source=str(path))


def calibration_from_option(
    calib: "str | Path | Sequence[float] | None", width: int, height: int, search: Sequence[Path] = (),
    owner: str = "reader",
) -> Intrinsics:
    """A reader's ``calib`` option: values, a file path, or None (then the first ``calib.txt`` in ``search``)."""
    if calib is None:
        for d in search:
            p = Path(d) / "calib.txt"
            if p.is_file():
                return read_calibration(p, width, height)
        where = ", ".join(str(Path(d) / "calib.txt") for d in search) or "(nowhere)"
        raise DatasetError(
            f"{owner}: no calibration: set 'calib' to a file or to [fx, fy, cx, cy, (k1, k2, p1, p2, (k3))]; "
            f"looked for {where}"
        )
    if isinstance(calib, (str, Path)):
        return read_calibration(Path(calib).expanduser(), width, height)
    return intrinsics_from_values(list(calib), width, height, source=f"{owner} config 'calib'")
