"""Viewers of runs.  :mod:`.rerun_viewer` logs a live run (a :class:`~pvslam_core.observer.RunObserver`) and
:mod:`.replay` a finished run directory to `rerun <https://rerun.io>`_; both need the optional ``viz`` extra
(``pip install 'pvslam[viz]'``).  Nothing in the core imports them unless a viewer is asked for."""
from __future__ import annotations

import os
import sys
from typing import Optional


class ViewerUnavailable(RuntimeError):
    """The viewer window cannot open here (no display); a recording file (``save``) still works."""


def display_problem() -> Optional[str]:
    """Why no viewer window can open on this machine (Linux without ``DISPLAY`` and ``WAYLAND_DISPLAY``), or None.

    Spawning rerun's viewer there does not fail: the SDK waits for a viewer that never connects."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (DISPLAY and WAYLAND_DISPLAY are unset)"
    return None
