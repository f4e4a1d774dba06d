"""bench/figures.py: the page of current figures and the README's Status table come from result files that name
their commit; a missing result is TBD with its command; results of a dirty tree or of other settings are refused."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import figures, provenance  # noqa: E402

SHA = "0123456789abcdef0123456789abcdef01234567"


def _prov(**kw):
    return {"commit": SHA, "dirty": False, "host": "vm", "cpus": 2, "libraries": {"torch": "x"}, "started": "t0",
            "finished": "t1", **kw}


def _cell(scenario, seed, pv, vo, init_s=0.5, posed=100):
    return {"scenario": scenario, "seed": seed, "set": "report" if seed else "shared", "frames": 100,
            "pvslam": {"ate_pct": pv, "init_s": init_s, "posed": posed, "frames": 100}, "vo": {"ate_pct": vo},
            "line": {"ate_pct": 5.0}}


def _matrix(name, seeds):
    rows = [_cell(sc, s, 0.1 * (k + 1), 2.0) for k, sc in enumerate(["busy_street", "handheld_fast"]) for s in seeds]
    rows += [_cell("kitti_06", None, 0.05, 2.1), _cell("kitti_01", None, 0.35, 6.5)]
    rows[-3]["vo"]["ate_pct"] = 0.5  # one cell only 2.5x below the VO
    return {"provenance": _prov(), "set": name, "seeds": seeds, "overrides": [], "frames": None, "size": [320, 240],
            "hfov_deg": None, "exposure": False, "rows": rows}


def _metrics(ate):
    return {"ate": {"rmse_percent_of_path": ate, "path_length": 324.7}, "loops": {"precision": 1.0, "recall": 1.0,
            "num_detected": 2}, "panoptic": {"pq": 1.0, "vpq": 0.998}, "timing": {"keyframes": 200}}


def _accuracy():
    names = ["online_ba+loop", "online_ba+loop (start 1)", "online_ba, no loop", "offline_ba+loop",
             "offline_ba, no loop"]
    return {"provenance": _prov(), "sections": ["accuracy", "peers"],
            "accuracy": {n: _metrics(a) for n, a in zip(names, [0.044, 0.05, 1.5, 0.06, 0.7])},
            "peers": {"textbook_vo": {"ate_pct": 2.6}}}


def _long():
    return {"provenance": _prov(), "sections": ["long"],
            "long": {"ate_pct": 0.0077, "path_m": 1996.0, "unmerged": 1, "loops": 118, "first_cpu": 0.06,
                     "last_cpu": 0.062, "peak_mb": 1372.0},
            "forced_loss": {"cut": {"separate_maps": 1}}}


@pytest.fixture
def results(tmp_path):
    d = tmp_path / "results"
    d.mkdir()
    for key, payload in (("report", _matrix("report", [3, 4, 5])), ("accuracy", _accuracy()), ("long", _long())):
        (d / f"{key}.json").write_text(json.dumps(payload))
    return d


def test_every_figure_is_read_or_tbd_with_its_command(results):
    rows, got = figures.load(results)
    by = {r.figure.key: r for r in rows}
    assert set(got) == {"report", "accuracy", "long"} and len(rows) == len(figures.FIGURES) <= 15
    flat = {"base": {"frames": 3000, "keyframes": 300, "peak_mb": 768.0, "ate_pct": 0.0072},
            "long": {"frames": 10000, "keyframes": 330, "peak_mb": 806.4, "ate_pct": 0.0031}}
    assert figures.endless({**_long(), "flat": flat}) == (
        "peak memory 0.75 / 0.79 GB at 3000 / 10000 frames (1.05x); 300 / 330 keyframes; ATE 0.0072 / 0.0031 %",
        "target: within 1.10x")
    assert by["report"].value == ("median 0.150 %, mean 0.163 %; **7 / 8** cells >= 3x below the VO; 8 / 8 "
                                  "initialised within 2 s, every frame posed")
    assert by["report"].compared == "textbook VO median 2.00 %; closest cell handheld_fast/5 (2.5x)"
    assert by["kitti"].value == "0.050 / 0.350 %" and "line 5.00 / 5.00 %" in by["kitti"].compared
    assert by["busy_street"].value == "0.100 / 0.100 / 0.100 %"
    assert by["default"].value.startswith("0.044 % of 325 m") and "textbook VO 2.60 %" == by["default"].compared
    assert by["long"].value == "0.0077 % of 2.0 km; 1 map, 118 loops" and by["long"].commit == SHA[:7]
    for key in ("heldout", "speed", "long_speed", "endless", "segmenter", "segmenter_pq",
                "loops_real"):  # endless: no "flat"
        assert by[key].value == figures.TBD and not by[key].commit
    table = figures.status_table(rows)
    assert len(table) == 2 + len(figures.FIGURES)
    assert any("`python bench/bench_matrix.py --set heldout --jobs 2 --json runs/bench/figures/heldout.json`" in t
               and figures.TBD in t for t in table)
    page = figures.page(rows, got)
    assert "## Report matrix, per cell" in page and "| busy_street/3 | report | 0.100 |" in page
    assert "Not measured yet (TBD)" in page and SHA in page


def test_heldout_counts_the_synthetic_cells_only(results):
    heldout = _matrix("heldout", [159, 160, 161])
    fig, _ = figures.matrix_summary(heldout, synthetic_only=True)
    assert "**5 / 6** cells" in fig and "5 / 6 initialised" not in fig


@pytest.mark.parametrize("change, message", [
    (lambda r: r["provenance"].update(dirty=True), "uncommitted changes"),
    (lambda r: r["provenance"].update(changed_during_run=True), "uncommitted changes"),
    (lambda r: r.update(overrides=["optimizer.iters=5"]), "not the plain report matrix"),
    (lambda r: r.update(set="tune"), "not the plain report matrix"),
    (lambda r: r.pop("provenance"), "no commit recorded"),
])
def test_results_of_another_tree_or_setting_are_refused(results, change, message):
    report = json.loads((results / "report.json").read_text())
    change(report)
    (results / "report.json").write_text(json.dumps(report))
    with pytest.raises((provenance.ProvenanceError, ValueError), match=message):
        figures.load(results)


def test_dirty_results_render_only_when_allowed(results):
    report = json.loads((results / "report.json").read_text())
    report["provenance"]["dirty"] = True
    (results / "report.json").write_text(json.dumps(report))
    rows, _ = figures.load(results, allow_dirty=True)
    assert {r.commit for r in rows if r.figure.bench == "report"} == {SHA[:7] + "+dirty"}


def test_the_readme_table_is_replaced_between_its_markers(results):
    rows, _ = figures.load(results)
    text = f"# x\n\nbefore\n{figures.BEGIN}\nold table\n{figures.END}\nafter\n"
    out = figures.readme_with(text, rows)
    assert out.startswith("# x\n\nbefore\n" + figures.BEGIN + "\n| what |") and out.endswith(figures.END + "\nafter\n")
    assert "old table" not in out
    with pytest.raises(ValueError, match="figures:begin"):
        figures.readme_with("# no markers\n", rows)


def test_render_only_writes_both_pages(results, tmp_path, monkeypatch, capsys):
    page, readme = tmp_path / "RESULTS.md", tmp_path / "README.md"
    readme.write_text(f"intro\n{figures.BEGIN}\n{figures.END}\n")
    monkeypatch.setattr(figures, "PAGE", page)
    monkeypatch.setattr(figures, "README", readme)
    assert figures.main(["--render-only", "--results", str(results)]) == 0
    assert page.read_text().startswith("# Current figures") and "| what | data |" in readme.read_text()
    assert "TBD: heldout" in capsys.readouterr().out


def test_the_figures_shown_measured_are_read_from_the_readme_table(results):
    rows, _ = figures.load(results)
    text = figures.readme_with(f"x\n{figures.BEGIN}\n{figures.END}\n", rows)
    shown = figures.shown_rows(text)
    assert set(shown) == {r.figure.what for r in rows if r.commit} and len(shown) >= 3
    assert any(not r.commit for r in rows)  # the TBD rows (commit "-") are not among them
    by = {r.figure.what: r for r in rows}
    assert all(shown[w] == (by[w].value, by[w].compared, by[w].commit) for w in shown)
    assert figures.shown_rows("no table here\n") == {}


def test_a_figure_without_its_result_here_keeps_what_the_pages_show(results, tmp_path, monkeypatch, capsys):
    page, readme = tmp_path / "RESULTS.md", tmp_path / "README.md"
    readme.write_text(f"intro\n{figures.BEGIN}\n{figures.END}\nend\n")
    monkeypatch.setattr(figures, "PAGE", page)
    monkeypatch.setattr(figures, "README", readme)
    assert figures.main(["--render-only", "--results", str(results)]) == 0
    first_page, first_readme = page.read_text(), readme.read_text()
    assert "## Report matrix, per cell" in first_page and "| report | `python bench/bench_matrix.py" in first_page
    # a fresh machine: only the long run's result file is here, measured at another commit
    other = tmp_path / "other"
    other.mkdir()
    long = json.loads((results / "long.json").read_text())
    long["provenance"]["commit"] = "fedcba9876543210fedcba9876543210fedcba98"
    long["long"]["ate_pct"] = 0.0123
    (other / "long.json").write_text(json.dumps(long))
    assert figures.main(["--render-only", "--results", str(other)]) == 0
    assert "kept as the pages showed them: " in capsys.readouterr().out
    rows = {r.figure.key: r for r in figures.load(other)[0]}
    shown = figures.shown_rows(readme.read_text())
    before = figures.shown_rows(first_readme)
    for key, r in rows.items():
        if r.figure.bench == "long" and r.commit:
            assert shown[r.figure.what][2] == "fedcba9" and shown[r.figure.what] != before[r.figure.what]
        elif r.figure.bench == "long":  # read from the file here and not in it: TBD, not kept
            assert r.figure.what not in shown
        else:  # the report, accuracy, ... rows as they were; the never-measured ones still TBD
            assert shown.get(r.figure.what) == before.get(r.figure.what)
    assert "0.0123 %" in page.read_text()
    # the per-cell sections and the Results lines of the benchmarks not measured here stay as they were
    new_sections, old_sections = figures._sections(page.read_text()), figures._sections(first_page)
    assert new_sections["Report matrix, per cell"] == old_sections["Report matrix, per cell"]
    assert new_sections["Default run and its ablation (driving loop, seed 0)"] == \
        old_sections["Default run and its ablation (driving loop, seed 0)"]
    results_lines = new_sections["Results"]
    assert any(x.startswith("| report |") for x in results_lines)
    assert any(x.startswith("| long |") and "fedcba98" in x for x in results_lines)
    assert "Not measured yet (TBD)" in page.read_text() and "`python bench/bench_matrix.py --set heldout" in \
        page.read_text().split("Not measured yet (TBD)")[1]
    # rendering again from the same files changes nothing
    again = page.read_text(), readme.read_text()
    assert figures.main(["--render-only", "--results", str(other)]) == 0
    assert (page.read_text(), readme.read_text()) == again


def test_a_benchmark_run_twice_by_two_figures_is_measured_once(tmp_path, monkeypatch):
    calls = []

    class Done:
        returncode = 0

    def fake_run(cmd, cwd, stdout, stderr):
        calls.append(cmd)
        Path(cmd[cmd.index("--json") + 1]).write_text("{}")
        return Done()

    monkeypatch.setattr(figures.subprocess, "run", fake_run)
    figures.run(["long", "long_speed"], tmp_path, jobs=2)
    assert len(calls) == 1 and (tmp_path / "long_speed.json").is_file()
    assert calls[0][1:] == ["bench/bench_pipeline.py", "--only", "long", "--json", str(tmp_path / "long.json")]


def test_the_speed_benchmarks_are_the_ones_skipped():
    assert {k for k, b in figures.BENCHES.items() if b.speed} == {"long_speed", "speed"}
    assert all(f.bench in figures.BENCHES for f in figures.FIGURES)


def _real(orb=True, orb_runs=3):
    def run(ate, posed, cpu=None):
        return {"ate_m": ate, "ate_all_m": 1.5 * ate, "posed": posed, "cpu_ms_per_frame": cpu, "first": first}
    rows = []
    for q, first, pv, same, o, vo in (("00", 14, 0.436, [0.416] * 3, [0.364, 0.457, 0.380], 3.436),
                                      ("06", 12, 0.024, [0.023] * 3, [0.057, 0.089, 0.087], 1.537),
                                      ("01", 0, 0.173, [0.019, 0.159], [0.031, 0.276], 3.348)):
        rows += [{"sequence": q, "method": "pvslam", "runs": [run(pv, 160, 190.0)]},
                 {"sequence": q, "method": "orbslam3", "runs": [run(a, 50, 110.0) for a in o] if orb else [],
                  "note": "" if orb else "no --orb-python (the python of a venv with pyorbslam3)"},
                 {"sequence": q, "method": "pvslam on ORB-SLAM3's frames", "runs": [run(a, 50) for a in same]},
                 {"sequence": q, "method": "textbook_vo", "runs": [run(vo, 160, 25.0)]}]
    return {"provenance": _prov(), "sequences": ["00", "06", "01"], "orb_runs": orb_runs, "rows": rows,
            "table": ["| sequence | method |", "|---|---|", "| 00 | pvslam |", "00 orbslam3, each run: ..."]}


def _figure(results, key, payload):
    """The row of figure ``key`` read from ``payload`` as its result file, with the rows and results read."""
    (results / f"{key}.json").write_text(json.dumps(payload))
    rows, got = figures.load(results)
    return {r.figure.key: r for r in rows}[key], rows, got


def test_the_real_excerpts_beside_orb_slam3_are_a_figure_with_the_full_table(results):
    row, rows, got = _figure(results, "real", _real())
    assert row.value == ("scored from frame 14 / 12 / 0 (the measured ground truth): pvslam 0.436 / 0.024 / 0.173 m; "
                         "on ORB-SLAM3's frames 0.416 / 0.023 / 0.019-0.159 m; all frames 0.654 / 0.036 / 0.259 m; "
                         "CPU 190 / 190 / 190 ms per frame")
    assert row.compared == ("ORB-SLAM3, 3 runs each: 0.364-0.457 / 0.057-0.089 / 0.031-0.276 m on 50 / 50 / 50 "
                            "frames, 110 / 110 / 110 ms; textbook VO 3.44 / 1.54 / 3.35 m")
    page = figures.page(rows, got)
    assert "## Real sequences beside ORB-SLAM3" in page and "| 00 | pvslam |" in page
    assert "- 00 orbslam3, each run: ..." in page  # the per-run lines below the table, not inside it
    assert figures.BENCHES["real"].shown() == "python bench/bench_real.py --json runs/bench/figures/real.json"
    spread = {**_real(), "size_spread": 2.0}
    assert figures.real_peers(spread)[0].startswith("scored from frame 14 / 12 / 0 (the measured ground truth): "
                                                    "pvslam 0.436 / 0.024 / 0.173 m (its processing size and 2 % "
                                                    "per side either way); on ORB-SLAM3's frames")


def test_the_real_figure_says_why_orb_slam3_is_missing_and_refuses_too_few_runs(results):
    (results / "real.json").write_text(json.dumps(_real(orb=False)))
    rows, _ = figures.load(results)
    assert {r.figure.key: r for r in rows}["real"].compared.startswith("ORB-SLAM3 not run (no --orb-python")
    (results / "real.json").write_text(json.dumps(_real(orb_runs=1)))
    with pytest.raises(ValueError, match="fewer than 3 ORB-SLAM3 runs"):
        figures.load(results)
    (results / "real.json").write_text(json.dumps({**_real(), "overrides": ["frontend.road.enabled=false"]}))
    with pytest.raises(ValueError, match="measured with overrides"):  # a screened variant is not the figures
        figures.load(results)


def _speed(orb=True):
    def row(group, run, fps, cpu, kf=0.45):
        return {"group": group, "run": run, "frames": 100, "kf_per_frame": kf, "fps": fps, "step_ms": {},
                "cpu_ms": cpu, "stage_ms": {}}
    rows = [row("default", "pvslam run", 16.5, 85.8), row("driving_loop", "seed 3", 17.9, 76.5),
            row("driving_loop", "mean", 16.6, 82.6), row("indoor_handheld", "mean", 31.3, 44.3, 0.19)]
    for seq, fps, cpu, orb_cpu in (("00", 10.3, 137.8, 106.1), ("06", 8.1, 177.1, 114.1)):
        rows += [row(f"KITTI {seq}", "pvslam run FOLDER --calib", fps, cpu),
                 row(f"KITTI {seq}", "textbook VO", 57.5, 25.9)]
        if orb:
            rows.append(row(f"KITTI {seq}", "ORB-SLAM3 (less vocabulary load)", float("nan"), orb_cpu))
    return {"provenance": _prov(), "sections": ["speed"], "speed": rows}


def test_the_speed_row_gives_each_scenario_mean_and_the_real_excerpts_beside_orb_slam3(results):
    row, rows, got = _figure(results, "speed", _speed())
    assert row.value == ("frames/s wall: default run 16.5 (0.45 keyframes a frame); scenario means driving_loop "
                         "16.6, indoor_handheld 31.3 (1 of 2 at 30 or more); 00 / 06 as a user runs them (native "
                         "size) 10.3 / 8.1, CPU 138 / 177 ms a frame, 1.3 / 1.6x ORB-SLAM3's")
    assert row.compared.startswith("targets 30 frames/s at 320x240")
    page = figures.page(rows, got)
    assert "## Speed per run and stage" in page and "| KITTI 06 | textbook VO | 100 | 0.45 | 57.5 |" in page
    row, _, _ = _figure(results, "speed", _speed(orb=False))
    assert row.value.endswith("- / -x ORB-SLAM3's (ORB-SLAM3 not run: no $PVSLAM_ORB_PYTHON / $PVSLAM_ORB_VOCAB)")
    (results / "speed.json").write_text(json.dumps({**_speed(), "overrides": ["optimizer.iters=2"]}))
    with pytest.raises(ValueError, match="measured with overrides"):
        figures.load(results)
