"""The current figures: runs the benchmark set and rewrites ``bench/RESULTS.md`` and the README's Status table.

    python bench/figures.py                  # every benchmark (about 1-2 hours on 2 quiet cores), then both pages
    python bench/figures.py --skip-speed     # accuracy only (a busy machine): the speed rows stay as they are
    python bench/figures.py --only report    # one benchmark (see --list), then both pages
    python bench/figures.py --render-only    # both pages from the result files already in --results
    python bench/figures.py --list           # the benchmarks, their commands and result files

Each benchmark is one bench tool command writing one result file into ``--results`` (default
``runs/bench/figures/``, ignored by git); the file records the commit it measured (:mod:`bench.provenance`).  Each
figure is one row read from a result: what, on which data (``tuned on``: the defaults were chosen on it; ``report``
and ``held out``: never tuned on, see ``bench/seeds.toml``), the figure, what it is compared with, the command, and
the commit.  Results of a dirty checkout or of a benchmark run with other settings (overrides, another seed set)
are refused.  Speed figures depend on the machine and its load: ``--skip-speed`` leaves them as they are.  Result
files stay on the machine that measured them (a fresh checkout has none), so a figure without its result file here
keeps the row, the per-cell section and the *Results* line the pages show now, with the commit they name: a part of
the set (``--only``) updates its figures and leaves the others as they were.  A figure the pages never showed
measured is TBD with its command.
"""
from __future__ import annotations

import argparse
import importlib
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from bench import provenance, seeds  # noqa: E402
from bench.figure_rows import (ablation, accuracy_section, default_run, endless, kitti, long_run,  # noqa: E402
                               long_speed, matrix_cells, matrix_scenario, matrix_summary, real_peers, real_section,
                               speed, speed_section)

PAGE = ROOT / "bench" / "RESULTS.md"
README = ROOT / "README.md"
DEFAULT_RESULTS = provenance.RESULTS_DIR / "figures"
BEGIN, END = "<!-- figures:begin -->", "<!-- figures:end -->"
TBD = "TBD (to be measured by the lead)"


# ------------------------------------------------------------------------------------------------ benchmarks
@dataclass(frozen=True)
class Bench:
    key: str                    # the result file is <results>/<key>.json
    argv: tuple[str, ...]       # the bench tool and its arguments; {json} = the result file, {jobs} = --jobs
    speed: bool = False         # its figures depend on the machine's load (skipped by --skip-speed)
    same_as: Optional[str] = None  # the same command as another benchmark: run once, one file each
    check: Optional[Callable[[dict], Optional[str]]] = None  # what is wrong with a result, or None

    def command(self, results: Path, jobs: int) -> list[str]:
        return [a.format(json=str(results / f"{self.key}.json"), jobs=jobs) for a in self.argv]

    def shown(self) -> str:
        rel = DEFAULT_RESULTS.relative_to(ROOT).as_posix()
        return "python " + " ".join(a.format(json=f"{rel}/{self.key}.json", jobs=2) for a in self.argv)


def _matrix_check(name: str) -> Callable[[dict], Optional[str]]:
    def check(r: dict) -> Optional[str]:
        if r.get("set") != name or r.get("overrides") or r.get("frames") or r.get("exposure") or r.get("hfov_deg") \
                or list(r.get("size") or [320, 240]) != [320, 240]:
            return f"not the plain {name} matrix (set {r.get('set')}, overrides {r.get('overrides')})"
        return None
    return check


def _pipeline_check(*sections: str) -> Callable[[dict], Optional[str]]:
    def check(r: dict) -> Optional[str]:
        if r.get("overrides"):
            return f"measured with overrides {r['overrides']}"
        missing = [s for s in sections if s not in (r.get("sections") or [])]
        return f"sections {missing} not measured" if missing else None
    return check


def _real_check(r: dict) -> Optional[str]:
    from bench.bench_real import SEQUENCES

    if r.get("overrides"):
        return f"measured with overrides {r['overrides']}"
    missing = [q for q in SEQUENCES if q not in (r.get("sequences") or [])]
    if missing:
        return f"KITTI excerpts {missing} not measured"
    return "fewer than 3 ORB-SLAM3 runs per excerpt" if r.get("orb_runs", 0) < 3 else None


BENCHES = {b.key: b for b in (
    Bench("report", ("bench/bench_matrix.py", "--set", "report", "--jobs", "{jobs}", "--json", "{json}"),
          check=_matrix_check("report")),
    Bench("heldout", ("bench/bench_matrix.py", "--set", "heldout", "--jobs", "{jobs}", "--json", "{json}"),
          check=_matrix_check("heldout")),
    Bench("accuracy", ("bench/bench_pipeline.py", "--only", "accuracy", "peers", "--no-colmap", "--json", "{json}"),
          check=_pipeline_check("accuracy", "peers")),
    Bench("long", ("bench/bench_pipeline.py", "--only", "long", "--json", "{json}"), check=_pipeline_check("long")),
    Bench("long_speed", ("bench/bench_pipeline.py", "--only", "long", "--json", "{json}"), speed=True,
          same_as="long", check=_pipeline_check("long")),
    Bench("speed", ("bench/bench_pipeline.py", "--only", "speed", "--json", "{json}"), speed=True,
          check=_pipeline_check("speed")),
    Bench("real", ("bench/bench_real.py", "--json", "{json}"), check=_real_check),
    Bench("segmenter", ("bench/bench_dynamic_masks.py", "--report", "--jobs", "{jobs}", "--json", "{json}"),
          check=lambda r: _tool("bench_dynamic_masks").report_problem(r)),
    Bench("segmenter_pq", ("bench/bench_domain.py", "--set", "segmenter", "--vps", "--json", "{json}"),
          check=lambda r: _tool("bench_domain").report_problem(r)),
    Bench("loops_real", ("bench/loops_real.py", "--json", "{json}"),
          check=lambda r: _tool("loops_real").report_problem(r)),
)}


def _tool(name: str):
    """The bench tool ``bench/<name>.py`` (its ``report_problem`` and ``figure``), imported on first use: torch loads
    then, not when the page is only rendered."""
    return importlib.import_module(f"bench.{name}")


# ------------------------------------------------------------------------------------------------ figures
@dataclass(frozen=True)
class Figure:
    key: str
    what: str
    data: str
    bench: str
    render: Callable[[dict], tuple[str, str]]


# the data column of the two segmenter rows: the ledger's seeds that no choice was made on
_SEGMENTER_SEEDS = f"held out (seeds {', '.join(map(str, seeds.load().sets['segmenter']))})"

FIGURES = (
    Figure("default", "default `pvslam run`: built-in driving loop, seed 0, 488 frames", "tuned on", "accuracy",
           default_run),
    Figure("report", "matrix: the synthetic scenarios x seeds 3-5 + KITTI 06 / 01 excerpts, no labels",
           "report", "report", matrix_summary),
    Figure("heldout", "matrix: the synthetic scenarios x seeds 159-161, no labels", "held out", "heldout",
           lambda r: matrix_summary(r, synthetic_only=True)),
    Figure("busy_street", "busy street (large vehicles, no segmenter), seeds 3 / 4 / 5", "report", "report",
           matrix_scenario("busy_street")),
    Figure("handheld_fast", "head camera (fast turns on the spot), seeds 3 / 4 / 5", "report", "report",
           matrix_scenario("handheld_fast")),
    Figure("kitti", "KITTI 06 / 01 excerpts (real, 51 frames each), no labels", "seen while tuning", "report", kitti),
    Figure("ablation", "Table 7 on the default run: loop closure and online vs offline BA", "tuned on", "accuracy",
           ablation),
    Figure("long", "3000-frame driving loop (6.7 laps), seed 0", "tuned on", "long", long_run),
    Figure("long_speed", "3000-frame driving loop: per-frame CPU over time, peak memory", "tuned on", "long_speed",
           long_speed),
    Figure("endless", "endless input: the driving loop as a live source (keyframes culled on revisits)", "tuned on",
           "long", endless),
    Figure("speed", "speed end to end (outputs written, evaluation excluded): the default run, every scenario's report "
           "seeds, the real excerpts as a user runs them", "report seeds (the default run tuned on)", "speed", speed),
    Figure("real", "KITTI 00 / 06 / 01 excerpts (real; 160 / 51 / 51 frames) as a user runs them, ATE Sim(3)",
           "00 chosen on, 06 / 01 seen while tuning", "real", real_peers),
    Figure("segmenter", "the shipped segmenter in looks it never saw: parked cars, a hand-held room, moving vehicles",
           _SEGMENTER_SEEDS, "segmenter",
           lambda r: _tool("bench_dynamic_masks").figure(r)),
    Figure("segmenter_pq", "the shipped segmenter's panoptic quality in looks it never saw (8 scenarios, 8 frames "
           "each) and the VPS heads' video panoptic quality",
           _SEGMENTER_SEEDS, "segmenter_pq",
           lambda r: _tool("bench_domain").figure(r)),
    Figure("loops_real", "the loop detectors on real frames: KITTI 00 / 06 / 01 excerpts (none revisits a place) and "
           "a revisit built from KITTI 00", "real (thresholds chosen on the generator)", "loops_real",
           lambda r: _tool("loops_real").figure(r)),
)


# ------------------------------------------------------------------------------------------------ reading
@dataclass
class Row:
    figure: Figure
    value: str
    compared: str
    commit: str     # short hash, "" when TBD
    note: str = ""  # why it is TBD, or where it was kept from


def load(results: Path, allow_dirty: bool = False) -> tuple[list[Row], dict[str, dict]]:
    """Every figure from its result file (or TBD), and the results read (key -> result)."""
    got: dict[str, dict] = {}
    for key, bench in BENCHES.items():
        path = results / f"{key}.json"
        if not path.is_file():
            continue
        r = provenance.read_json(path)
        prov = r["provenance"]
        if (prov.get("dirty") or prov.get("changed_during_run")) and not allow_dirty:
            raise provenance.ProvenanceError(f"{path}: measured on a checkout with uncommitted changes "
                                             f"(commit {prov['commit'][:10]}); rerun on a clean checkout")
        bad = bench.check(r) if bench.check else None
        if bad:
            raise ValueError(f"{path}: {bad}; rerun `{bench.shown()}`")
        got[key] = r
    rows = []
    for f in FIGURES:
        if f.bench not in got:
            rows.append(Row(f, TBD, "", "", note="no result"))
            continue
        r = got[f.bench]
        shown = f.render(r)
        if shown is None:
            rows.append(Row(f, TBD, "", "", note=f"not in {f.bench}.json"))
            continue
        value, compared = shown
        prov = r["provenance"]
        rows.append(Row(f, value, compared, prov["commit"][:7] + ("+dirty" if prov.get("dirty") else "")))
    return rows, got


# ------------------------------------------------------------------------------------------------ pages
def status_table(rows: list[Row]) -> list[str]:
    """The README's Status table (and the page's summary): one row per figure, its command and commit."""
    out = ["| what | data | figure | compared with | command | commit |", "|---|---|---|---|---|---|"]
    for row in rows:
        cmd = BENCHES[row.figure.bench].shown()
        out.append(f"| {row.figure.what} | {row.figure.data} | {row.value} | {row.compared or '-'} | `{cmd}` | "
                   f"{row.commit or '-'} |")
    return out


def _sections(text: str) -> dict[str, list[str]]:
    """The ``## `` sections of a page: title -> its lines between the heading and the next, blank lines around them
    dropped (a missing page has none)."""
    out: dict[str, list[str]] = {}
    for chunk in ("\n" + text).split("\n## ")[1:]:
        title, _, body = chunk.partition("\n")
        out[title] = body.strip("\n").splitlines()
    return out


#: the page's sections under the summary: result key, title, lines from the result
SECTIONS = (("report", "Report matrix, per cell", matrix_cells),
            ("heldout", "Held-out matrix, per cell", matrix_cells),
            ("accuracy", "Default run and its ablation (driving loop, seed 0)", accuracy_section),
            ("real", "Real sequences beside ORB-SLAM3 and the textbook VO (`bench/bench_real.py`)", real_section),
            ("speed", "Speed per run and stage (`bench/bench_pipeline.py --only speed`)", speed_section))


def page(rows: list[Row], got: dict[str, dict], old_page: str = "") -> str:
    """The page of current figures; a section or *Results* line whose result file is not here is kept from
    ``old_page`` (the page as it is now)."""
    lines = [
        "# Current figures",
        "",
        "Generated by `python bench/figures.py` from the result files of the benchmarks below; do not edit by hand.",
        "Every figure is of the commit it names (the library code measured) on the machine named under *Results*.",
        "The pipeline is deterministic: a figure repeats exactly on one machine and moves slightly with the CPU and",
        "library versions. ATE is the Sim(3)-aligned RMSE over every frame in % of the ground-truth path length.",
        "*tuned on*: the defaults were chosen on these data; *report* (seeds 3-5) and *held out* (seeds 159-161):",
        "never tuned on (`bench/seeds.toml`); the KITTI excerpts run with every seed set, so tuning saw them.",
        "Why each default is what it is: [docs/decisions.md](../docs/decisions.md). Earlier experiments and their",
        "logs are in the git history (`git show 652fac9:bench/RESULTS.md`).",
        "",
        "## Summary",
        "",
        *status_table(rows),
    ]
    old = _sections(old_page)
    for key, title, render in SECTIONS:
        body = render(got[key]) if key in got else old.get(title)
        if body:
            lines += ["", f"## {title}", "", *body]
    lines += ["", "## Results", "",
              "| result | command | commit | dirty | machine | started | finished |", "|---|---|---|---|---|---|---|"]
    kept = {line.split("|")[1].strip(): line for line in old.get("Results", []) if line.startswith("| ")}
    for key in BENCHES:
        if key in got:
            p = got[key]["provenance"]
            lines.append(f"| {key} | `{BENCHES[key].shown()}` | {p['commit']} | {p.get('dirty')} | "
                         f"{p.get('host', '?')}, {p.get('cpus', '?')} CPUs, torch "
                         f"{(p.get('libraries') or {}).get('torch')} | {p.get('started', '?')} | "
                         f"{p.get('finished', '?')} |")
        elif key in kept and any(r.commit and r.figure.bench == key for r in rows):
            lines.append(kept[key])
    missing = sorted({r.figure.bench for r in rows if not r.commit}, key=list(BENCHES).index)
    if missing:
        lines += ["", "Not measured yet (TBD): " + ", ".join(f"`{BENCHES[k].shown()}`" for k in missing) + "."]
    return "\n".join(lines) + "\n"


def shown_rows(text: str) -> dict[str, tuple[str, str, str]]:
    """The figures the README's Status table in ``text`` shows measured (with a commit): what -> (figure, compared
    with, commit)."""
    if BEGIN not in text or END not in text:
        return {}
    block = text.split(BEGIN, 1)[1].split(END, 1)[0]
    out = {}
    for line in block.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and len(cells) == 6 and cells[0] != "what" and cells[-1] not in ("", "-"):
            out[cells[0]] = (cells[2], "" if cells[3] == "-" else cells[3], cells[5])
    return out


def kept_rows(rows: list[Row], readme: str) -> list[Row]:
    """``rows`` where a figure without a result file here takes the row the README shows measured now."""
    shown = shown_rows(readme)
    return [Row(r.figure, *shown[r.figure.what], note="kept: no result file here")
            if r.note == "no result" and r.figure.what in shown else r for r in rows]


def readme_with(text: str, rows: list[Row]) -> str:
    """``text`` (the README) with the table between its figures markers replaced."""
    if BEGIN not in text or END not in text:
        raise ValueError(f"README.md has no {BEGIN} ... {END} block for the Status table")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return head + BEGIN + "\n" + "\n".join(status_table(rows)) + "\n" + END + tail


# ------------------------------------------------------------------------------------------------ running
def run(keys: list[str], results: Path, jobs: int) -> None:
    results.mkdir(parents=True, exist_ok=True)
    done: dict[tuple[str, ...], str] = {}
    for key in keys:
        b = BENCHES[key]
        if b.argv in done:  # the same command already ran: one measurement, a file per benchmark
            shutil.copyfile(results / f"{done[b.argv]}.json", results / f"{key}.json")
            continue
        cmd = [sys.executable, *b.command(results, jobs)]
        print(f"== {key}: {' '.join(cmd[1:])}", flush=True)
        with open(results / f"{key}.log", "w") as log:
            rc = subprocess.run(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT).returncode
        if rc != 0:
            raise SystemExit(f"{key} failed (exit {rc}); see {results / f'{key}.log'}")
        done[b.argv] = key


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--results", type=Path, default=DEFAULT_RESULTS, help="folder of the result files")
    ap.add_argument("--only", nargs="+", choices=list(BENCHES), help="run only these benchmarks")
    ap.add_argument("--skip-speed", action="store_true", help="do not run the speed benchmarks")
    ap.add_argument("--render-only", action="store_true", help="run nothing; rewrite the pages from --results")
    ap.add_argument("--jobs", type=int, default=2, help="parallel cells of the matrices (default 2)")
    ap.add_argument("--allow-dirty", action="store_true", help="accept results of a checkout with changes "
                    "(marked +dirty; not for a committed page)")
    ap.add_argument("--list", action="store_true", help="print the benchmarks and their commands")
    args = ap.parse_args(argv)
    if args.list:
        for b in BENCHES.values():
            print(f"{b.key:<11} {'speed ' if b.speed else ''}{b.shown()}")
        return 0
    if not args.render_only:
        try:
            provenance.check(args.results / "x.json")
        except provenance.ProvenanceError as exc:
            return provenance.fail(exc)
        keys = args.only or [k for k, b in BENCHES.items() if not (b.speed and args.skip_speed)]
        keys = sorted(keys, key=lambda k: BENCHES[k].same_as is not None)  # the originals first
        for k in list(keys):
            src = BENCHES[k].same_as
            if src and src not in keys:
                keys.insert(0, src)
        run(keys, args.results, args.jobs)
    try:
        rows, got = load(args.results, args.allow_dirty)
    except (provenance.ProvenanceError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    # result files are per machine (ignored by git): what was not measured here keeps the row the pages show now
    readme = README.read_text(encoding="utf-8")
    rows = kept_rows(rows, readme)
    old_page = PAGE.read_text(encoding="utf-8") if PAGE.is_file() else ""
    PAGE.write_text(page(rows, got, old_page), encoding="utf-8")
    README.write_text(readme_with(readme, rows), encoding="utf-8")
    tbd = [r.figure.key for r in rows if not r.commit]
    kept = [r.figure.key for r in rows if r.note.startswith("kept")]
    print(f"wrote {PAGE} and the Status table of {README} ({len(rows)} figures"
          + (f"; kept as the pages showed them: {', '.join(kept)}" if kept else "")
          + (f"; TBD: {', '.join(tbd)}" if tbd else "") + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
