"""pvslam: plugin-based panoptic visual SLAM (PV-SLAM) in plain PyTorch.

Public API (imported lazily so that the command line starts fast)::

    from pvslam_core import load_config, run_config, run_ablation, evaluate_run_dir
    from pvslam_core import run_path, Tracker       # your own video / image folder; frames one at a time
    from pvslam_core import Pipeline, hookimpl, PluginConfig
    from pvslam_core.types import Frame, Intrinsics, PanopticSegmentation      # data types and conventions
    from pvslam_core.interfaces import Segmenter, Frontend, LoopDetector, Optimizer, VPSHead, DatasetReader
"""
from __future__ import annotations

from typing import Any

__all__ = [
    "load_config", "load_ablation", "run_config", "run_ablation", "evaluate_run_dir", "run_path", "Tracker",
    "Pipeline",
    "hookimpl", "PluginConfig", "ConfigError", "PluginError", "get_registry",
]

_LAZY = {
    "load_config": ("config", "load_config"),
    "load_ablation": ("config", "load_ablation"),
    "ConfigError": ("config", "ConfigError"),
    "run_config": ("api", "run_config"),
    "run_ablation": ("api", "run_ablation"),
    "evaluate_run_dir": ("api", "evaluate_run_dir"),
    "run_path": ("api", "run_path"),
    "Tracker": ("tracker", "Tracker"),
    "Pipeline": ("pipeline", "Pipeline"),
    "hookimpl": ("registry", "hookimpl"),
    "PluginError": ("registry", "PluginError"),
    "get_registry": ("registry", "get_registry"),
    "PluginConfig": ("config_base", "PluginConfig"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        mod, attr = _LAZY[name]
        return getattr(importlib.import_module(f"{__name__}.{mod}"), attr)
    raise AttributeError(f"module 'pvslam_core' has no attribute {name!r}")
