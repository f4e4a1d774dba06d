"""Viewers of runs.  :mod:`.rerun_viewer` logs a live run (a :class:`~pvslam_core.observer.RunObserver`) and
:mod:`.replay` a finished run directory to `rerun <https://rerun.io>`_; both need the optional ``viz`` extra
(``pip install 'pvslam[viz]'``).  Nothing in the core imports them unless a viewer is asked for."""
