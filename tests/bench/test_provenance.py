"""A benchmark result names the commit of the code it measured, or is not written (bench/provenance.py), and the
tools that write result files refuse before they measure anything."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import bench_matrix, provenance  # noqa: E402


def _git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.email=t@t", "-c", "user.name=t", *args], cwd=cwd, check=True,
                          capture_output=True, text=True).stdout


@pytest.fixture
def repo(tmp_path, monkeypatch):
    """A one-commit git checkout outside any other (GIT_CEILING_DIRECTORIES stops the search at tmp_path)."""
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path))
    root = tmp_path / "repo"
    root.mkdir()
    _git(root, "init", "-q")
    (root / "a.py").write_text("x = 1\n")
    _git(root, "add", "a.py")
    _git(root, "commit", "-q", "-m", "one")
    return root


def test_this_checkout_has_a_commit_and_a_dirty_flag():
    prov = provenance.provenance(["bench/x.py"])
    assert len(prov["commit"]) == 40 and isinstance(prov["dirty"], bool)
    assert prov["argv"] == ["bench/x.py"] and prov["cpus"] >= 1
    assert (prov["diff_sha256"] is None) == (not prov["dirty"])


def test_dirty_means_changed_tracked_files_and_the_diff_is_hashed(repo):
    clean = provenance.checkout_state(repo)
    assert clean["commit"] == _git(repo, "rev-parse", "HEAD").strip() and clean["dirty"] is False
    (repo / "notes.txt").write_text("untracked: not part of the measured code\n")
    assert provenance.checkout_state(repo)["dirty"] is False
    (repo / "a.py").write_text("x = 2\n")
    one = provenance.checkout_state(repo)
    (repo / "a.py").write_text("x = 3\n")
    two = provenance.checkout_state(repo)
    assert one["dirty"] and two["dirty"] and one["diff_sha256"] != two["diff_sha256"]


def test_no_checkout_no_result(tmp_path, monkeypatch):
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path))
    plain = tmp_path / "export"
    plain.mkdir()
    with pytest.raises(provenance.ProvenanceError, match="not in a git checkout"):
        provenance.checkout_state(plain)
    monkeypatch.setattr(provenance, "library_dir", lambda: plain)
    with pytest.raises(provenance.ProvenanceError, match="no result is written"):
        provenance.check(tmp_path / "r.json")


def test_tools_and_library_from_different_checkouts_are_refused(repo, monkeypatch):
    monkeypatch.setattr(provenance, "library_dir", lambda: repo)
    with pytest.raises(provenance.ProvenanceError, match="would measure pvslam_core imported from"):
        provenance.provenance()


def test_result_files_stay_out_of_bench(tmp_path):
    with pytest.raises(provenance.ProvenanceError, match="do not go into bench/"):
        provenance.write_json(ROOT / "bench" / "results_x.json", {"a": 1})
    assert not (ROOT / "bench" / "results_x.json").exists()
    assert provenance.check_path(tmp_path / "ok.json") == (tmp_path / "ok.json").resolve()


def test_written_results_carry_the_provenance_and_read_back(tmp_path):
    prov = provenance.check(tmp_path / "r.json", argv=["x"])
    path = provenance.write_json(tmp_path / "sub" / "r.json", {"rows": [1, 2]}, prov)
    data = provenance.read_json(path)
    assert data["rows"] == [1, 2] and data["provenance"]["commit"] == prov["commit"]
    assert "finished" in data["provenance"] and "changed_during_run" not in data["provenance"]
    text = provenance.write_text(tmp_path / "t.md", "| a |\n", prov).read_text()
    head = json.loads(text.splitlines()[0].removeprefix("<!-- provenance: ").removesuffix(" -->"))
    assert head["commit"] == prov["commit"] and text.endswith("| a |\n")


def test_a_checkout_that_changed_while_measuring_is_marked(tmp_path, monkeypatch):
    prov = provenance.check(tmp_path / "r.json")
    state = provenance.checkout_state(provenance.library_dir())
    monkeypatch.setattr(provenance, "checkout_state", lambda p: {**state, "diff_sha256": "other", "dirty": True})
    data = provenance.read_json(provenance.write_json(tmp_path / "r.json", {}, prov))
    assert data["provenance"]["changed_during_run"] is True


def test_a_result_without_a_commit_is_not_read(tmp_path):
    (tmp_path / "old.json").write_text(json.dumps({"commit": "unknown", "rows": []}))
    with pytest.raises(provenance.ProvenanceError, match="no commit recorded"):
        provenance.read_json(tmp_path / "old.json")
    sha = "0123456789abcdef0123456789abcdef01234567"
    (tmp_path / "legacy.json").write_text(json.dumps({"commit": sha, "rows": []}))
    assert provenance.read_json(tmp_path / "legacy.json")["provenance"] == {"commit": sha, "dirty": None}


def test_the_matrix_refuses_before_it_measures(tmp_path, monkeypatch, capsys):
    ran = []
    monkeypatch.setattr(bench_matrix, "run_cell", lambda c: ran.append(c))

    def no_git(path):
        raise provenance.ProvenanceError(f"{path} is not in a git checkout (test)")

    monkeypatch.setattr(provenance, "checkout_state", no_git)
    args = ["--scenarios", "busy_street", "--seeds", "3", "--out", str(tmp_path)]
    assert bench_matrix.main(args + ["--json", str(tmp_path / "r.json")]) == 2
    assert "error:" in capsys.readouterr().err and not ran and not (tmp_path / "r.json").exists()
    monkeypatch.undo()
    monkeypatch.setattr(bench_matrix, "run_cell", lambda c: ran.append(c))
    assert bench_matrix.main(args + ["--json", str(ROOT / "bench" / "r.json")]) == 2
    assert not ran and "do not go into bench/" in capsys.readouterr().err


def test_the_pipeline_bench_refuses_before_it_measures(tmp_path, monkeypatch):
    from bench import bench_pipeline

    monkeypatch.setattr(bench_pipeline, "section_accuracy", lambda *a: pytest.fail("measured without a commit"))
    monkeypatch.setattr(sys, "argv", ["bench_pipeline.py", "--only", "accuracy", "--json",
                                      str(ROOT / "bench" / "results_pipeline_accuracy.json")])
    with pytest.raises(SystemExit) as exc:
        bench_pipeline.main()
    assert exc.value.code == 2
