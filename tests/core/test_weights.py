"""`pvslam weights` and resolve_weights() against a real HTTP server on 127.0.0.1 (no outside network).

The server serves in-memory files and counts requests per path, so "cached" means "no second request", not "the
function returned quickly".  Checksums in the test catalogue are computed here with hashlib, independently of
pvslam_core.weights.
"""
from __future__ import annotations

import hashlib
import http.server
import json
import socket
import threading
import warnings
from collections import Counter

import pytest

from pvslam_core import weights as W
from pvslam_core.cli import main

PAYLOAD = bytes(range(256)) * 4096 + b"pvslam"  # ~1 MB: several read chunks
SHA = hashlib.sha256(PAYLOAD).hexdigest()
MD5 = hashlib.md5(PAYLOAD).hexdigest()


class _Handler(http.server.BaseHTTPRequestHandler):
    files: dict = {}
    hits: Counter = Counter()

    def do_GET(self):  # noqa: N802 (http.server API)
        self.hits[self.path] += 1
        if self.path == "/page.html":
            body = b"<html>confirm download</html>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
            return
        if self.path == "/truncated.pth":  # announces more bytes than it sends, then closes
            self.send_response(200)
            self.send_header("Content-Type", "application/octet-stream")
            self.send_header("Content-Length", str(len(PAYLOAD)))
            self.end_headers()
            self.wfile.write(PAYLOAD[:1000])
            self.close_connection = True
            return
        body = self.files.get(self.path)
        if body is None:
            self.send_error(404, "Not Found")
            return
        self.send_response(200)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):  # keep pytest output clean
        pass


@pytest.fixture(scope="module")
def server():
    _Handler.files = {"/good-1234.pth": PAYLOAD, "/model_final_abc.pkl": PAYLOAD, "/nohash.pth": PAYLOAD}
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}"
    srv.shutdown()
    srv.server_close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def catalog(tmp_path, monkeypatch, server):
    """A registry.toml whose weights live on the local server, and an empty cache."""
    dead = f"http://127.0.0.1:{_free_port()}"
    text = f'''
[[plugin]]
name = "fakeplug"
interface = "loop"
entry_point = "nowhere"
description = "test"

[[plugin.weights]]
name = "full-sha"
aliases = ["good-1234.pth"]
url = "{server}/good-1234.pth"
sha256 = "{SHA}"
license = "MIT"
used_by = "fakeplug, variant a"

[[plugin.weights]]
name = "sha-prefix"
url = "{server}/good-1234.pth"
filename = "prefixed.pth"
sha256 = "{SHA[:8].upper()}"
license = "MIT"

[[plugin.weights]]
name = "md5-prefix"
url = "{server}/model_final_abc.pkl"
md5 = "{MD5[:6]}"
license = "MIT"

[[plugin.weights]]
name = "bad-sha"
url = "{server}/good-1234.pth"
filename = "bad.pth"
sha256 = "{hashlib.sha256(b'other').hexdigest()}"
license = "MIT"

[[plugin.weights]]
name = "bad-prefix"
url = "{server}/good-1234.pth"
filename = "badprefix.pth"
sha256 = "{'0' if SHA[0] != '0' else '1'}{SHA[1:8]}"
license = "MIT"

[[plugin.weights]]
name = "nohash"
url = "{server}/nohash.pth"
license = "MIT"
note = "no published checksum"

[[plugin.weights]]
name = "missing"
url = "{server}/missing.pth"
sha256 = "{SHA}"
license = "MIT"

[[plugin.weights]]
name = "offline"
url = "{dead}/x.pth"
sha256 = "{SHA}"
license = "MIT"

[[plugin.weights]]
name = "html"
url = "{server}/page.html"
filename = "page.pth"
license = "MIT"

[[plugin.weights]]
name = "truncated"
url = "{server}/truncated.pth"
license = "MIT"

[[plugin.weights]]
name = "byhand"
url = "https://example.invalid/share"
filename = "byhand.pth"
manual = true
license = "none stated"
note = "share page only"
'''
    reg = tmp_path / "registry.toml"
    reg.write_text(text)
    monkeypatch.setenv("PVSLAM_REGISTRY", str(reg))
    monkeypatch.setenv("PVSLAM_CACHE", str(tmp_path / "cache"))
    for var in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("no_proxy", "127.0.0.1,localhost")
    _Handler.hits.clear()
    return tmp_path / "cache" / "weights"


def _no_partials(cache):
    return not cache.exists() or not [p for p in cache.iterdir() if p.name.startswith(".")]


def test_fetch_verifies_full_sha_and_caches(catalog):
    p = W.fetch("full-sha", progress=False)
    assert p == catalog / "good-1234.pth" and p.read_bytes() == PAYLOAD
    assert _Handler.hits["/good-1234.pth"] == 1
    assert W.fetch("full-sha") == p and W.resolve_weights("good-1234.pth") == p  # alias, from the cache
    assert _Handler.hits["/good-1234.pth"] == 1  # no second download
    W.fetch("full-sha", force=True)
    assert _Handler.hits["/good-1234.pth"] == 2
    assert _no_partials(catalog)


def test_prefix_checksums_sha256_and_md5(catalog):
    assert W.fetch("sha-prefix").read_bytes() == PAYLOAD  # upper-case prefix in the catalogue is accepted
    assert W.fetch("md5-prefix").name == "model_final_abc.pkl"
    assert W.expected_checksum(W.lookup("sha-prefix")).describe().startswith("sha256 prefix")
    assert W.expected_checksum(W.lookup("full-sha")).describe() == f"full sha256 {SHA}"


@pytest.mark.parametrize("name,kind", [("bad-sha", "full sha256"), ("bad-prefix", "sha256 prefix")])
def test_checksum_mismatch_removes_file(catalog, name, kind):
    with pytest.raises(W.WeightsError) as ei:
        W.fetch(name)
    msg = str(ei.value)
    assert "checksum mismatch" in msg and kind in msg and SHA in msg and "removed" in msg
    assert not W.cached_path(name).exists() and _no_partials(catalog)


def test_missing_hash_downloads_with_explicit_warning(catalog):
    with pytest.warns(W.UnverifiedWeightsWarning, match=f"NOT verified.*{SHA}"):
        p = W.fetch("nohash")
    assert p.read_bytes() == PAYLOAD
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert W.fetch("nohash") == p  # cached: no second download, no second warning
    assert _Handler.hits["/nohash.pth"] == 1


def test_http_404_names_url(catalog):
    with pytest.raises(W.WeightsError, match=r"HTTP 404 .*/missing\.pth"):
        W.fetch("missing")
    assert _no_partials(catalog)


def test_unreachable_suggests_offline_path(catalog):
    with pytest.raises(W.WeightsError) as ei:
        W.fetch("offline", timeout=5)
    msg = str(ei.value)
    assert "cannot reach http://127.0.0.1:" in msg and 'weights = "/path/to/file"' in msg


def test_html_page_and_truncated_download_are_refused(catalog):
    with pytest.raises(W.WeightsError, match="HTML page"):
        W.fetch("html")
    with pytest.raises(W.WeightsError, match="truncated|broke off"):
        W.fetch("truncated")
    assert not W.cached_path("html").exists() and not W.cached_path("truncated").exists()
    assert _no_partials(catalog)


def test_manual_entry_explains_and_accepts_a_copied_file(catalog):
    with pytest.raises(W.WeightsError, match="cannot be downloaded automatically.*share page only"):
        W.fetch("byhand")
    dest = W.cached_path("byhand")
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_bytes(b"x")
    assert W.fetch("byhand") == dest


def test_resolve_path_spec_and_unknown_name(catalog, tmp_path):
    f = tmp_path / "mine.pth"
    f.write_bytes(b"abc")
    assert W.resolve_weights(str(f)) == f.resolve() and W.resolve_weights(f) == f.resolve()
    with pytest.raises(W.WeightsError) as ei:
        W.resolve_weights("deit-bse")
    msg = str(ei.value)
    assert "no such file" in msg and "full-sha" in msg and "md5-prefix" in msg
    with pytest.raises(W.WeightsError, match="not a file"):
        W.resolve_weights(str(tmp_path))
    with pytest.raises(W.WeightsError, match="unknown weights 'nope'; known names: full-sha, sha-prefix"):
        W.fetch("nope")


def test_google_drive_share_url_becomes_direct():
    w = W.Weights(name="d", url="https://drive.google.com/file/d/AbC_-12/view?usp=sharing")
    assert W.download_url(w) == "https://drive.google.com/uc?export=download&id=AbC_-12"
    assert W.file_name(W.Weights(name="d", url="https://x/a/b.pth?dl=1")) == "b.pth"
    with pytest.raises(W.WeightsError, match="filename"):
        W.file_name(W.Weights(name="d", url="https://x/a/", filename="../evil"))


def test_cli_list_fetch_path(catalog, capsys):
    assert main(["weights", "path", "full-sha"]) == 1
    out, err = capsys.readouterr()
    assert out.strip() == str(catalog / "good-1234.pth") and "weights fetch full-sha" in err
    assert main(["weights", "fetch", "full-sha"]) == 0
    assert capsys.readouterr().out.strip() == str(catalog / "good-1234.pth")
    assert main(["weights", "path", "good-1234.pth"]) == 0
    capsys.readouterr()
    assert main(["weights", "list", "--json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["full-sha"]["cached"] and not rows["md5-prefix"]["cached"]
    assert rows["full-sha"]["plugin"] == "fakeplug" and rows["nohash"]["checksum"].startswith("none")
    assert main(["weights", "list"]) == 0
    assert "cached" in capsys.readouterr().out
    assert main(["weights", "fetch", "bad-sha"]) == 1
    assert "checksum mismatch" in capsys.readouterr().err
    assert main(["weights", "fetch", "--force", "full-sha"]) == 0
    assert _Handler.hits["/good-1234.pth"] == 3  # bad-sha shares the URL; --force downloads again


def test_shipped_catalogue_entries_are_complete():
    """Every shipped entry: https URL, licence, a usable checksum or an explicit note why there is none."""
    import os

    old = os.environ.pop("PVSLAM_REGISTRY", None)
    try:
        entries = W.catalog_weights()
    finally:
        if old is not None:
            os.environ["PVSLAM_REGISTRY"] = old
    names = {w.name for w in entries}
    assert {"droid", "deit-base", "deit-base-distilled", "panoptic-fpn-r50-3x-coco", "pvo-panfpn-vkitti2",
            "pvo-vo-vkitti2"} <= names
    for w in entries:
        assert w.url.startswith("https://") and w.license and w.used_by
        W.file_name(w)
        chk = W.expected_checksum(w)
        if chk is None:
            assert "checksum" in w.note.lower(), w.name
    assert W.expected_checksum(W.find("deit-base", entries)) == W.Expected("sha256", "b5f2ef4d")
    assert W.expected_checksum(W.find("panoptic-fpn-r50-3x-coco", entries)) == W.Expected("md5", "c10459")


def test_a_cached_file_is_verified_again_before_use(catalog):
    p = W.fetch("full-sha", progress=False)
    p.write_bytes(PAYLOAD[:-1] + b"X")  # changed on disk after the download (bit rot, an edit, a bad copy)
    with pytest.raises(W.WeightsError) as ei:
        W.resolve_weights("full-sha")
    msg = str(ei.value)
    assert "does not match its checksum" in msg and str(p) in msg and "pvslam weights fetch full-sha --force" in msg
    assert _Handler.hits["/good-1234.pth"] == 1  # refused, not silently downloaded again
    assert W.fetch("full-sha", force=True).read_bytes() == PAYLOAD
    assert W.resolve_weights("full-sha") == p  # the fresh copy passes
    dest = W.cached_path("md5-prefix")  # a file copied into the cache by hand is checked too
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_bytes(b"version https://git-lfs.github.com/spec/v1\noid sha256:0\n")
    with pytest.raises(W.WeightsError, match="Git LFS pointer: run `git lfs pull`"):
        W.fetch("md5-prefix")
