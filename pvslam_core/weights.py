"""Checkpoints of the learned plugins: the ``[[plugin.weights]]`` catalogue, a download cache, ``weights = ...``.

A plugin config's ``weights`` value is either a catalogue name (``"deit-base"``, or an alias such as the upstream
file name) -- fetched once into the cache and reused -- or the path of a local file::

    from pvslam_core.weights import resolve_weights
    path = resolve_weights(cfg.weights)        # Path of an existing file, downloaded and verified if needed

Cache: ``$PVSLAM_CACHE/weights`` (the same root as the synthetic sequences), else ``$XDG_CACHE_HOME/pvslam/weights``,
else ``%LOCALAPPDATA%/pvslam/weights`` on Windows, else ``~/.cache/pvslam/weights``.  A download streams into a
temporary file in the cache folder, is verified, and is renamed onto its final name only then, so the cache never
holds a partial or unverified file; a cached file is hashed again before each use (a file changed on disk since, or
copied there by hand, is refused with the command that downloads it again).

Checksums: ``sha256`` or ``md5`` in the catalogue, either the full hex digest or a prefix of it (torch.hub file names
carry a SHA-256 prefix, detectron2 model-zoo names an MD5 prefix).  An entry without any checksum is downloaded
unverified with a warning that shows the SHA-256 to record.  Only the standard library is used here (plus tqdm for
the progress bar, and torch inside :func:`load_torch_file`), so ``pvslam weights`` starts fast and the module is
importable without torch.

Files the plugins load themselves go through the same checks: :func:`check_shipped` compares a file shipped with a
plugin with the SHA-256 the plugin records for it, and :func:`load_torch_file` reads a torch file with
``weights_only=True``; both name a Git LFS pointer as such, and every failure is one line naming the file.
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


def file_digest(path: Union[str, os.PathLike], algo: str = "sha256") -> str:
    """One hex digest of a file, read in chunks."""
    h = hashlib.new(algo)
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(_CHUNK), b""):
            h.update(chunk)
    return h.hexdigest()


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
        _verify_cached(w, dest)
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


def _verify_cached(w: Weights, path: Path) -> None:
    """A cached file against its catalogued checksum (none recorded: nothing to check)."""
    expected = expected_checksum(w)
    if expected is None:
        return
    got = file_digest(path, expected.algo)
    if not got.startswith(expected.digest):
        lfs = " (a Git LFS pointer: run `git lfs pull`)" if is_lfs_pointer(path) else ""
        raise WeightsError(
            f"weights {w.name!r}: the cached file {path} does not match its checksum{lfs}: expected "
            f"{expected.describe()}, got {expected.algo} {got}; download it again with `pvslam weights fetch "
            f"{w.name} --force`, or delete the file")


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


# ------------------------------------------------------------------------------------------- local files --
#: the first bytes of a Git LFS pointer file (a checkout without ``git lfs pull`` holds these instead of the data)
LFS_POINTER = b"version https://git-lfs"
_UNSAFE = re.compile(r"GLOBAL (\S+) (?:was not an allowed global|whose module \S+ is blocked)")


def is_lfs_pointer(path: Union[str, os.PathLike]) -> bool:
    """Whether the file starts like a Git LFS pointer."""
    try:
        with open(path, "rb") as fh:
            return fh.read(len(LFS_POINTER)) == LFS_POINTER
    except OSError:
        return False


def _lfs_message(what: str, path: Path) -> str:
    return f"{what}: {path} is a Git LFS pointer, not the weights: run `git lfs pull`"


def refuse_lfs_pointer(path: Union[str, os.PathLike], what: str, error: type[Exception] = WeightsError) -> None:
    """Raise ``error`` saying "Git LFS pointer: run `git lfs pull`" when the file is one."""
    if is_lfs_pointer(path):
        raise error(_lfs_message(what, Path(path)))


def check_shipped(path: Union[str, os.PathLike], sha256: str, what: str, fix: str,
                  error: type[Exception] = WeightsError) -> Path:
    """``path``, a weights file shipped with a plugin, checked against the full SHA-256 the plugin records for it:
    a missing file raises :class:`FileNotFoundError`, other bytes (a truncated copy, a Git LFS pointer, a replaced
    file) ``error``; both name ``what`` (the plugin and setting), the file and ``fix`` (what to do)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{what}: the shipped file {p} is missing; {fix}")
    got = file_digest(p)
    if got != sha256.lower():
        if is_lfs_pointer(p):
            raise error(f"{_lfs_message(what, p)}; {fix}")
        raise error(f"{what}: the shipped file {p} is corrupt or was replaced: sha256 {got[:16]}..., "
                    f"{p.stat().st_size} bytes, expected {sha256[:16]}...; {fix}")
    return p


def load_torch_file(path: Union[str, os.PathLike], what: str, error: type[Exception] = WeightsError,
                    refused: Optional[type[Exception]] = None) -> object:
    """``torch.load(path, map_location="cpu", weights_only=True)`` with one-line errors that name ``what`` and the
    file: a missing file, a Git LFS pointer and a file that is not a torch file raise ``error``; a file whose pickle
    asks for objects ``weights_only`` does not build (they could run code) raises ``refused`` (default ``error``)."""
    import pickle

    import torch

    p = Path(path)
    if not p.is_file():
        raise error(f"{what}: {p}: no such file")
    refuse_lfs_pointer(p, what, error)
    try:
        return torch.load(p, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        text = str(exc)
        m = _UNSAFE.search(text)
        if m:
            raise (refused or error)(
                f"{what}: {p}: refused - the file holds objects that torch.load(weights_only=True) will not "
                f"unpickle ({m.group(1)}; loading them could run code); re-save only the tensors "
                "(a state_dict) on a trusted machine") from None
        raise error(f"{what}: {p}: not a readable torch file ({_torch_reason(text)})") from None
    except Exception as exc:  # noqa: BLE001 - zip, storage and pickle errors of a file that is not a torch file
        raise error(f"{what}: {p}: not a readable torch file ({type(exc).__name__}: "
                    f"{_torch_reason(str(exc))})") from None


def _torch_reason(text: str) -> str:
    """The one informative line of torch.load's message (it wraps the pickle error in advice about weights_only)."""
    if text.startswith("Weights only load failed"):
        parts = [t.strip() for t in text.split("\n\n") if t.strip()]
        text = parts[1] if len(parts) >= 3 else parts[0][len("Weights only load failed."):]
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return (lines[0] if lines else "no details")[:200]
