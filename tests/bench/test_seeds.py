"""The seed ledger (bench/seeds.toml via bench/seeds.py): one data file says which seeds were tuned on, reported on
and spent; the tools read it and it stays consistent."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import seeds  # noqa: E402


def test_the_shipped_ledger_is_consistent():
    led = seeds.load()
    assert led.sets["default"] == (0,) and set(led.sets["tune"]) == {1, 2, 6, 7, 8}
    assert set(led.sets["report"]) == {3, 4, 5} and len(led.sets["heldout"]) == 3
    for k, r in enumerate(led.spent):  # sorted, disjoint, each with its use
        assert r.first <= r.last and r.use and (k == 0 or r.first > led.spent[k - 1].last)
    assert [led.set_of(s) for s in (0, 1, 3, 9, 158, 159)] == ["default", "tune", "report", "used", "used", "heldout"]
    fresh = led.fresh(3)
    assert len(fresh) == 3 and all(led.set_of(s) == "fresh" for s in fresh)
    assert all(s in led.spent_seeds or led.set_of(s) != "fresh" for s in range(fresh[0]))  # every lower one is seen


def test_fresh_seeds_skip_the_learned_plugins_ranges(tmp_path):
    (tmp_path / "l.toml").write_text('[sets]\ndefault = [0]\ntune = [1]\nreport = [2]\n'
                                     '[[spent]]\nseeds = [3, 4]\nuse = "a"\n[[spent]]\nseeds = [6, 7]\nuse = "b"\n')
    led = seeds.load(tmp_path / "l.toml")
    assert led.fresh(3) == [5, 8, 9] and led.spent_seeds == (3, 4, 6, 7)


@pytest.mark.parametrize("body, message", [
    ('[sets]\ndefault = [0]\ntune = [1, 2]\nreport = [2]\n', "share seeds"),
    ('[sets]\ndefault = [0]\ntune = [1]\n', "report is missing"),
    ('[sets]\ndefault = [0]\ntune = [1]\nreport = [2]\n[[spent]]\nseeds = [5, 9]\nuse = "a"\n'
     '[[spent]]\nseeds = [9, 12]\nuse = "b"\n', "overlaps"),
    ('[sets]\ndefault = [0]\ntune = [1]\nreport = [2]\n[[spent]]\nseeds = [1, 3]\nuse = "a"\n', "named set"),
    ('[sets]\ndefault = [0]\ntune = [1]\nreport = [2]\n[[spent]]\nseeds = [5, 6]\n', "says no use"),
])
def test_an_inconsistent_ledger_is_refused(tmp_path, body, message):
    (tmp_path / "l.toml").write_text(body)
    with pytest.raises(seeds.LedgerError, match=message):
        seeds.load(tmp_path / "l.toml")


def test_the_command_prints_sets_and_fresh_seeds(capsys):
    assert seeds.main([]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert "next fresh:" in out and any(ln.split(None, 1) == ["report", "3, 4, 5"] for ln in lines)
    # one column for the seeds, whatever the longest set name
    starts = {len(ln) - len(ln.split(None, 1)[1]) for ln in lines if not ln.startswith("next")}
    assert len(starts) == 1
    assert seeds.main(["--fresh", "2"]) == 0
    assert capsys.readouterr().out.split() == [str(s) for s in seeds.load().fresh(2)]
