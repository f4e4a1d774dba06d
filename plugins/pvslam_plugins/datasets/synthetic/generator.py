"""Built-in synthetic sequences with exact ground truth: generate, cache, list.

``generate(scenario, out_dir=None, ...)`` renders a scenario (see :data:`SCENARIOS`) and writes it in the layout
described in :mod:`.writer` (and the plugin's ``README.md``).  With ``out_dir=None`` the sequence goes to the
cache: ``$PVSLAM_CACHE`` or ``$XDG_CACHE_HOME/pvslam`` or ``~/.cache/pvslam``, then
``synthetic/<scenario>-<W>x<H>-<hash>`` where the hash covers every parameter and the generator version, so a
cached folder is reused only for exactly the same request.  Writing goes to a temporary folder renamed at the
end: a crash never leaves a half cache, and a killed writer's temporary folder is removed by the next start
(:mod:`.staging`).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Optional

from .domain import check_domain
from .render import check_hfov
from .scenarios import DEFAULT_SCENARIO, SCENARIOS, UnknownScenarioError, build, check_name, revision
from .staging import sweep_stale
from .writer import GENERATOR_VERSION, write_sequence

__all__ = ["SCENARIOS", "DEFAULT_SCENARIO", "UnknownScenarioError", "generate", "ensure_cached", "cache_root",
           "cache_path", "is_complete"]


def cache_root() -> Path:
    """``$PVSLAM_CACHE``, else ``$XDG_CACHE_HOME/pvslam``, else ``~/.cache/pvslam``."""
    if os.environ.get("PVSLAM_CACHE"):
        return Path(os.environ["PVSLAM_CACHE"]).expanduser()
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]).expanduser() / "pvslam"
    return Path.home() / ".cache" / "pvslam"


def _params(scenario: str, num_frames: Optional[int], width: int, height: int, seed: int,
            laps: Optional[float], hfov_deg: Optional[float] = None, domain: Optional[str] = None) -> dict:
    p = {"scenario": scenario, "num_frames": num_frames, "width": int(width), "height": int(height),
         "seed": int(seed), "laps": laps, "version": GENERATOR_VERSION}
    if hfov_deg is not None:  # another camera; the default camera's cache keys stay as they were
        p["hfov_deg"] = float(check_hfov(hfov_deg))
    if domain is not None:  # a restyled scene (domain randomisation); the plain scenes' keys stay as they were
        p["domain"] = check_domain(domain)
    if revision(scenario, seed):  # only where the content changed: every other cache key stays as it was
        p["revision"] = revision(scenario, seed)
    return p


def cache_path(scenario: str = DEFAULT_SCENARIO, *, num_frames: Optional[int] = None, width: int = 320,
               height: int = 240, seed: int = 0, laps: Optional[float] = None,
               hfov_deg: Optional[float] = None, domain: Optional[str] = None) -> Path:
    """Where :func:`ensure_cached` keeps this request."""
    check_name(scenario)
    p = _params(scenario, num_frames, width, height, seed, laps, hfov_deg, domain)
    h = hashlib.sha1(json.dumps(p, sort_keys=True).encode()).hexdigest()[:10]
    return cache_root() / "synthetic" / f"{scenario}-{int(width)}x{int(height)}-{h}"


def is_complete(root: Path) -> bool:
    """A finished sequence folder (``meta.json`` is written last)."""
    return (Path(root) / "meta.json").is_file()


def _matches(root: Path, scenario: str, num_frames: Optional[int], width: int, height: int, seed: int,
             laps: Optional[float], hfov_deg: Optional[float], domain: Optional[str]) -> bool:
    try:
        meta = json.loads((root / "meta.json").read_text())
    except (OSError, ValueError):
        return False
    same = (meta.get("scenario") == scenario and meta.get("width") == width and meta.get("height") == height
            and meta.get("seed") == seed and meta.get("version") == GENERATOR_VERSION and meta.get("laps") == laps
            and meta.get("revision", 0) == revision(scenario, seed)
            and meta.get("hfov_deg") == (None if hfov_deg is None else float(hfov_deg))
            and meta.get("domain") == domain)
    return same and (num_frames is None or meta.get("num_frames") == num_frames)


def generate(scenario: str = DEFAULT_SCENARIO, out_dir: Optional[Path] = None, *, num_frames: Optional[int] = None,
             width: int = 320, height: int = 240, seed: int = 0, progress: bool = True,
             laps: Optional[float] = None, hfov_deg: Optional[float] = None, domain: Optional[str] = None) -> Path:
    """Render ``scenario`` and write it to ``out_dir`` (None: the cache); returns the sequence folder.

    ``num_frames`` None = the scenario's default length (``laps`` sets it for the looping scenarios, e.g.
    ``laps=6.8`` gives about 3000 frames of ``driving_loop``); ``hfov_deg`` another camera's horizontal field of view
    (None: the default camera, about 61 degrees); ``domain`` a domain-randomisation split (:mod:`.domain`; None: the
    plain scene).  An existing folder that already holds exactly this
    sequence is returned as it is; one holding anything else is an error (nothing is overwritten).
    """
    check_name(scenario)
    if out_dir is None:
        return ensure_cached(scenario, num_frames=num_frames, width=width, height=height, seed=seed,
                             progress=progress, laps=laps, hfov_deg=hfov_deg, domain=domain)
    out = Path(out_dir)
    if out.exists():
        if _matches(out, scenario, num_frames, width, height, seed, laps, hfov_deg, domain):
            return out
        if not out.is_dir() or any(out.iterdir()):
            raise FileExistsError(f"{out} exists and does not hold this synthetic sequence; choose an empty or new "
                                  "folder (nothing is overwritten)")
    sc = build(scenario, num_frames=num_frames, width=width, height=height, seed=seed, laps=laps, hfov_deg=hfov_deg,
               domain=domain)
    return write_sequence(sc, out, progress=progress)


def ensure_cached(scenario: str = DEFAULT_SCENARIO, *, num_frames: Optional[int] = None, width: int = 320,
                  height: int = 240, seed: int = 0, progress: bool = True, laps: Optional[float] = None,
                  hfov_deg: Optional[float] = None, domain: Optional[str] = None) -> Path:
    """The cached folder of this request, generated first if it is not there yet."""
    root = cache_path(scenario, num_frames=num_frames, width=width, height=height, seed=seed, laps=laps,
                      hfov_deg=hfov_deg, domain=domain)
    sweep_stale(root.parent)  # what a killed writer left (SIGKILL: no handler ran)
    if is_complete(root):
        return root
    sc = build(scenario, num_frames=num_frames, width=width, height=height, seed=seed, laps=laps, hfov_deg=hfov_deg,
               domain=domain)
    try:
        return write_sequence(sc, root, progress=progress)
    except OSError:
        if is_complete(root):  # another process finished the same sequence first
            return root
        raise
