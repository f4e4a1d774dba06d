"""Which dataset reader opens a path: ``pvslam run clip.mp4`` / ``pvslam run frames/`` / a KITTI or TUM folder.

The core knows no reader by name.  Each dataset plugin may register an extra ``detect(path) -> DatasetMatch | None``
(``register("name", factory, Config, detect=detect)``) that looks at the path -- cheaply: names and small text
files, never decoding a whole video -- and says how specific its match is and which config options open it.  The
most specific match wins (a KITTI ``image_2`` folder is also a plain image folder: the ``kitti`` match scores
higher).  Scores: 1.0 for a layout identified by its own files (``rgb.txt``, ``mav0/``, ``sequences/NN``), 0.9 for
a file type (a video extension), 0.5 for a generic folder of images.

With a config (``pvslam run PATH --config FILE``), :func:`merge_config_section` keeps the config's ``[dataset]``
keys the detected reader has (a ``resize``, ``stride``, ``end`` ...); the path sets the reader and where the data
is.  A match lists in ``guessed`` the options it chose without reading them from the path (KITTI's camera when
the path is a sequence folder): a config for the same reader may set those.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from ..config import ConfigError

LOG = logging.getLogger("pvslam")


@dataclass
class DatasetMatch:
    """A plugin's answer: how specific the match is (0..1), the config options that open it, and what it is."""

    score: float
    options: dict[str, Any] = field(default_factory=dict)
    description: str = ""
    guessed: tuple[str, ...] = ()  # options picked for the path, not read from it: a config for the reader may set them


@dataclass
class Detection:
    plugin: str
    options: dict[str, Any]
    score: float
    description: str
    others: list[tuple[str, float]] = field(default_factory=list)  # the other plugins that matched, with scores
    guessed: tuple[str, ...] = ()

    def section(self) -> dict[str, Any]:
        """The ``[dataset]`` table of a config: ``{"plugin": ..., **options}``."""
        return {"plugin": self.plugin, **self.options}


class DetectionError(ConfigError):
    """No installed dataset plugin recognises the path (the message lists what was asked); a usage error, like a
    configuration error (exit status 2 on the command line)."""


def detect_dataset(path: str | Path, registry=None) -> Detection:
    """Ask every dataset plugin with a ``detect`` extra about ``path``; the highest score wins."""
    from ..registry import get_registry

    reg = registry or get_registry()
    p = Path(str(path)).expanduser()
    matches: list[tuple[float, str, DatasetMatch]] = []
    asked: list[str] = []
    for name in reg.names("dataset"):
        detect = reg.get("dataset", name).extras.get("detect")
        if detect is None:
            continue
        asked.append(name)
        try:
            m = detect(p)
        except Exception as exc:  # noqa: BLE001 - one plugin's bug must not hide the others' answers
            LOG.debug("dataset plugin %r failed to inspect %s: %s: %s", name, p, type(exc).__name__, exc)
            continue
        if m is not None and m.score > 0:
            matches.append((float(m.score), name, m))
    if not matches:
        if not p.exists():
            raise DetectionError(f"{p}: no such file or folder")
        kind = "folder" if p.is_dir() else "file"
        raise DetectionError(
            f"{p}: no dataset plugin recognises this {kind}; expected a video file, a folder of images or a dataset "
            f"layout one of the installed readers knows ({', '.join(asked) or 'none can detect'}); or give a config "
            "with a [dataset] table (--config)")
    matches.sort(key=lambda t: (-t[0], t[1]))
    score, name, best = matches[0]
    if len(matches) > 1 and matches[1][0] == score:
        tied = ", ".join(n for s, n, _ in matches if s == score)
        LOG.warning("%s: recognised equally well by %s; using %s", p, tied, name)
    return Detection(name, dict(best.options), score, best.description or name,
                     [(n, s) for s, n, _ in matches[1:]], tuple(best.guessed))


def dataset_section(path: str | Path, calib: Optional[str | Path] = None, registry=None) -> Detection:
    """:func:`detect_dataset` plus ``calib``: the calibration file goes to the reader's ``calib`` option; a reader
    that has no such option (its layout carries the calibration) is an error rather than a silently ignored file."""
    from ..registry import get_registry

    reg = registry or get_registry()
    det = detect_dataset(path, reg)
    if calib is not None:
        c = Path(str(calib)).expanduser()
        if not c.is_file():
            raise ConfigError(f"--calib {calib}: calibration file not found")
        model = reg.get("dataset", det.plugin).config_model
        if "calib" not in getattr(model, "model_fields", {}):
            raise ConfigError(f"--calib {calib}: the {det.plugin} reader takes its calibration from the dataset "
                              f"({det.description}); it has no 'calib' option")
        det.options["calib"] = str(c)
    return det


def merge_config_section(det: Detection, table: dict[str, Any],
                         registry=None) -> tuple[dict[str, Any], list[str], dict[str, list[str]]]:
    """The ``[dataset]`` table of a run on a path with a config: the detected reader and the options the path
    sets (a config for the same reader, or for none, may set its ``guessed`` ones), plus the config table's other
    keys where the detected reader has them (``resize``, ``stride``, ``end``, a ``calib`` ...).  Returns the table,
    the config keys taken, and the config keys dropped by why (the reader has no such option, or, from a config
    for another reader, a value this one does not accept)."""
    from pydantic import ValidationError

    from ..registry import get_registry

    model = (registry or get_registry()).get("dataset", det.plugin).config_model
    fields = getattr(model, "model_fields", {})
    same = str(table.get("plugin", det.plugin)) == det.plugin  # a table without `plugin` is for any reader
    section, taken = det.section(), []
    absent, invalid = f"the {det.plugin} reader has no such option", f"not a valid {det.plugin} option"
    dropped: dict[str, list[str]] = {absent: [], invalid: []}
    for key, value in table.items():
        if key == "plugin" or (key in det.options and not (same and key in det.guessed)):
            continue  # the path sets it
        if key not in fields:
            dropped[absent].append(key)
            continue
        if not same:
            try:
                model.model_validate({**det.options, **{k: section[k] for k in taken}, key: value})
            except ValidationError:
                dropped[invalid].append(f"{key}={value!r}")
                continue
        section[key] = value
        taken.append(key)
    return section, taken, {why: keys for why, keys in dropped.items() if keys}


def run_name_for(path: str | Path) -> str:
    """A run name from the input path (``clip.mp4`` -> ``clip``), safe as one folder name."""
    p = Path(str(path)).expanduser()
    stem = (p.stem if p.is_file() else p.name) or p.resolve().name or "run"
    return re.sub(r"[^\w.-]+", "_", stem).strip("._")[:80] or "run"
