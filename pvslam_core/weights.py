"""Checkpoints of the learned plugins: the ``[[plugin.weights]]`` catalogue, a download cache, ``weights = ...``.

A plugin config's ``weights`` value is either a catalogue name (``"deit-base"``, or an alias such as the upstream
file name) -- fetched once into the cache and reused -- or the path of a local file::

    from pvslam_core.weights import resolve_weights
    path = resolve_weights(cfg.weights)        # Path of an existing file, downloaded and verified if needed

Cache: ``$PVSLAM_CACHE/weights`` (the same root as the synthetic sequences), else ``$XDG_CACHE_HOME/pvslam/weights``,
else ``%LOCALAPPDATA%/pvslam/weights`` on Windows, else ``~/.cache/pvslam/weights``.  A download streams into a
temporary file in the cache folder, is verified, and is renamed onto its final name only then, so the cache never
holds a partial or unverified file: a cached file is a verified (or, without a catalogued checksum, a complete)
download and is not hashed again.

Checksums: ``sha256`` or ``md5`` in the catalogue, either the full hex digest or a prefix of it (torch.hub file names
carry a SHA-256 prefix, detectron2 model-zoo names an MD5 prefix).  An entry without any checksum is downloaded
unverified with a warning that shows the SHA-256 to record.  Only the standard library is used here (plus tqdm for
the progress bar), so ``pvslam weights`` starts fast and the module is importable without torch.
"""
from __future__ import annotations

import hashlib
import http.client
import logging
import os
import re
import socket
import sys
import urllib.error
import urllib.request
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

from .catalog import Weights, load_catalog

LOG = logging.getLogger("pvslam")

OFFLINE_HINT = ('on a machine without network access, download the file elsewhere and set weights = '
                '"/path/to/file" in the plugin\'s config section')
_CHUNK = 1 << 20
_HEX = re.compile(r"^[0-9a-f]+$")
_GDRIVE = re.compile(r"^https://drive\.google\.com/file/d/([A-Za-z0-9_-]+)")


class WeightsError(RuntimeError):
    """A checkpoint cannot be found, downloaded or verified; the message says which, where and what to do."""


class UnverifiedWeightsWarning(UserWarning):
    """A download that could not be verified because the catalogue holds no checksum for it."""


# ------------------------------------------------------------------------------------------------ cache --
def cache_dir() -> Path:
    """The weights cache folder (not created here)."""
    if os.environ.get("PVSLAM_CACHE"):
        return Path(os.environ["PVSLAM_CACHE"]).expanduser() / "weights"
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]).expanduser() / "pvslam" / "weights"
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        return Path(os.environ["LOCALAPPDATA"]) / "pvslam" / "weights"
    return Path.home() / ".cache" / "pvslam" / "weights"


def catalog_weights() -> list[Weights]:
    """Every ``[[plugin.weights]]`` entry of the catalogue, in file order."""
    return [w for entry in load_catalog() for w in entry.weights]


def find(name: str, entries: Optional[list[Weights]] = None) -> Optional[Weights]:
    """The entry whose name or alias is ``name`` (exact match), or None."""
    for w in entries if entries is not None else catalog_weights():
        if name == w.name or name in w.aliases:
            return w
    return None


def lookup(name: str) -> Weights:
    entries = catalog_weights()
    w = find(name, entries)
    if w is None:
        raise WeightsError(f"unknown weights {name!r}; known names: {_known(entries)} (`pvslam weights list`)")
    return w


def _known(entries: list[Weights]) -> str:
    return ", ".join(w.name for w in entries) or "(none: registry.toml has no [[plugin.weights]])"


def file_name(w: Weights) -> str:
    name = w.filename or w.url.split("?", 1)[0].rstrip("/").rsplit("/", 1)[-1]
    # A cache name must stay a plain file name inside the cache folder, whatever the catalogue says.
    if not name or name in (".", "..") or "/" in name or "\\" in name:
        raise WeightsError(f"weights {w.name!r}: cannot derive a file name from {w.url!r}; set `filename` in "
                           "registry.toml")
    return name


def cached_path(w: Union[Weights, str]) -> Path:
    """Where ``w`` lives in the cache (it may not be there yet)."""
    w = lookup(w) if isinstance(w, str) else w
    return cache_dir() / file_name(w)


# --------------------------------------------------------------------------------------------- checksum --
@dataclass(frozen=True)
class Expected:
    algo: str  # "sha256" | "md5"
    digest: str  # lower-case hex, full or prefix

    @property
    def is_prefix(self) -> bool:
        return len(self.digest) < hashlib.new(self.algo).digest_size * 2

    def describe(self) -> str:
        if self.is_prefix:
            return f"{self.algo} prefix {self.digest!r} ({len(self.digest)} hex digits, as in the file name)"
        return f"full {self.algo} {self.digest}"


def expected_checksum(w: Weights) -> Optional[Expected]:
    """The catalogued checksum (SHA-256 preferred over MD5), or None when none is known."""
    for algo in ("sha256", "md5"):
        digest = getattr(w, algo).strip().lower()
        if not digest:
            continue
        full = hashlib.new(algo).digest_size * 2
        if not _HEX.match(digest) or len(digest) > full:
            raise WeightsError(f"registry.toml: weights {w.name!r}: {algo} = {digest!r} is not a hex digest or a "
                               f"prefix of one (at most {full} hex digits)")
        return Expected(algo, digest)
    return None


def file_digests(path: Path) -> dict[str, str]:
    """SHA-256 and MD5 of a file, read in chunks."""
    h = {"sha256": hashlib.sha256(), "md5": hashlib.md5()}
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(_CHUNK), b""):
            for d in h.values():
                d.update(chunk)
    return {k: d.hexdigest() for k, d in h.items()}


# --------------------------------------------------------------------------------------------- download --
def download_url(w: Weights) -> str:
    """The URL to GET: a Google Drive share page becomes its direct-download form (small files need no confirm)."""
    m = _GDRIVE.match(w.url)
    if m:
        return f"https://drive.google.com/uc?export=download&id={m.group(1)}"
    return w.url


def fetch(name: str, force: bool = False, progress: bool = True, timeout: float = 30.0) -> Path:
    """The cached file of catalogue entry ``name``, downloaded and verified first if it is not cached
    (``force``: download again even when cached)."""
    w = lookup(name)
    dest = cached_path(w)
    if dest.is_file() and not force:
        return dest
    if w.manual:
        raise WeightsError(
            f"weights {w.name!r} cannot be downloaded automatically: {w.note or w.url}\n"
            f"  get the file by hand from {w.url}, then copy it to {dest} or set weights = \"/path/to/file\" "
            "in the plugin's config section")
    expected = expected_checksum(w)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.part-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        digests = _download(download_url(w), tmp, w, progress, timeout)
        _verify(w, expected, digests, dest)
        os.replace(tmp, dest)  # atomic: the cache only ever holds complete, verified files
    finally:
        tmp.unlink(missing_ok=True)
    return dest


def _download(url: str, tmp: Path, w: Weights, progress: bool, timeout: float) -> dict[str, str]:
    """Stream ``url`` into ``tmp``; returns the SHA-256 and MD5 computed on the way."""
    from tqdm import tqdm

    req = urllib.request.Request(url, headers={"User-Agent": "pvslam-weights"})
    try:
        resp = urllib.request.urlopen(req, timeout=timeout)
    except urllib.error.HTTPError as exc:
        raise WeightsError(f"weights {w.name!r}: HTTP {exc.code} {exc.reason} from {url}") from None
    except (urllib.error.URLError, socket.timeout, ConnectionError) as exc:
        reason = getattr(exc, "reason", exc)
        raise WeightsError(f"weights {w.name!r}: cannot reach {url} ({reason}); {OFFLINE_HINT}") from None
    h = {"sha256": hashlib.sha256(), "md5": hashlib.md5()}
    with resp:
        ctype = resp.headers.get("Content-Type", "")
        if ctype.startswith("text/html"):
            # Share pages (Google Drive's virus-scan confirmation, login walls) answer 200 with HTML.
            raise WeightsError(f"weights {w.name!r}: {url} returned an HTML page, not the file (a confirmation "
                               f"or login page); download it in a browser and {OFFLINE_HINT}")
        total = resp.headers.get("Content-Length")
        total = int(total) if total and total.isdigit() else None
        got = 0
        with open(tmp, "wb") as out, tqdm(total=total, unit="B", unit_scale=True, unit_divisor=1024,
                                          desc=file_name(w), leave=False,
                                          disable=not (progress and sys.stderr.isatty())) as bar:
            try:
                for chunk in iter(lambda: resp.read(_CHUNK), b""):
                    out.write(chunk)
                    for d in h.values():
                        d.update(chunk)
                    got += len(chunk)
                    bar.update(len(chunk))
            except (OSError, socket.timeout, http.client.HTTPException) as exc:
                raise WeightsError(f"weights {w.name!r}: download from {url} broke off after {got} bytes "
                                   f"({exc}); run the fetch again, or {OFFLINE_HINT}") from None
    if total is not None and got != total:
        raise WeightsError(f"weights {w.name!r}: download from {url} is truncated: {got} of {total} bytes; "
                           "run the fetch again")
    return {k: d.hexdigest() for k, d in h.items()}


def _verify(w: Weights, expected: Optional[Expected], digests: dict[str, str], dest: Path) -> None:
    if expected is None:
        msg = (f"weights {w.name!r}: registry.toml holds no checksum for this file, so the download was NOT "
               f"verified (sha256 {digests['sha256']}; record it in registry.toml once you trust the file)")
        warnings.warn(msg, UnverifiedWeightsWarning, stacklevel=3)
        LOG.warning(msg)
        return
    got = digests[expected.algo]
    if not got.startswith(expected.digest):
        raise WeightsError(
            f"weights {w.name!r}: checksum mismatch for {w.url}: expected {expected.describe()}, got {expected.algo} "
            f"{got}; the downloaded file was removed (not cached at {dest}). Run the fetch again; if it persists, "
            "the file on the server changed")


# ------------------------------------------------------------------------------------------------ specs --
def resolve_weights(spec: Union[str, os.PathLike], progress: bool = True) -> Path:
    """A plugin's ``weights`` value -> the path of an existing file.

    A catalogue name or alias (exact match) is fetched into the cache (or found there); anything else is a path,
    which must name an existing file.  Write ``./droid.pth`` for a local file that shares a catalogue alias.
    """
    text = os.fspath(spec)
    if not text:
        raise WeightsError("weights: empty value; give a catalogue name (`pvslam weights list`) or a file path")
    if not isinstance(spec, Path):
        entries = catalog_weights()
        w = find(text, entries)
        if w is not None:
            return fetch(w.name, progress=progress)
    else:
        entries = None
    p = Path(text).expanduser()
    if p.is_file():
        return p.resolve()
    if p.exists():
        raise WeightsError(f"weights {text!r}: {p} is not a file")
    known = _known(entries if entries is not None else catalog_weights())
    raise WeightsError(f"weights {text!r}: no such file ({p.resolve()}) and not a catalogue name; known names: "
                       f"{known}")
