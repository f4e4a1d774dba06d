"""Fixtures of the sweep tests; the sweep file helpers are in sweep_helpers.py."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(scope="session")
def synth_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("pvslam_cache")


@pytest.fixture
def cache_env(monkeypatch, synth_cache):
    """Generated sequences go to a session folder (shared by the tests, never the user's cache)."""
    monkeypatch.setenv("PVSLAM_CACHE", str(synth_cache))
    return synth_cache
