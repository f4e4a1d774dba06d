"""The ``pvslam`` command line.  Heavy libraries (torch, OpenCV, evo) are imported only inside commands, so
``pvslam --help`` answers at once."""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Optional

EXIT_CONFIG = 2
EXIT_RUNTIME = 1
EXIT_NO_MOTION = 3  # the run finished but estimated no motion


def _add_config_args(p: argparse.ArgumentParser, required: bool = False) -> None:
    p.add_argument("--config", "-c", required=required, metavar="FILE",
                   help="pipeline TOML (or an ablation TOML with [[variant]] tables, or a run's config.json)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override one config value, e.g. --set loop.plugin=none (repeatable; TOML value syntax, "
                   "null for an optional key's None)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pvslam",
        description="Panoptic visual SLAM: monocular video in; trajectory, depth/point cloud and temporally "
                    "consistent panoptic segmentation out.",
        epilog="Run with no config to process the built-in synthetic driving loop: pvslam run",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_run, _add_plugins, _add_config, _add_synth, _add_eval, _add_view, _add_export, _add_train,
                _add_weights, _add_sweep):
        add(sub)
    return parser


def _add_run(sub) -> None:
    p = sub.add_parser("run", help="run the pipeline (or every variant of an ablation file)")
    _add_config_args(p)
    p.add_argument("--output-dir", help="folder for run directories (overrides run.output_dir)")
    p.add_argument("--name", help="run name (overrides run.name)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar, only the summary")
    p.add_argument("path", nargs="?", metavar="PATH",
                   help="input: a video file, a folder of images, a KITTI / EuRoC / TUM sequence folder or a camera "
                        "index; the reader is detected from it (replaces the config's [dataset])")
    p.add_argument("--calib", metavar="FILE",
                   help="calibration of PATH: 'fx fy cx cy [k1 k2 p1 p2 [k3 [k4 k5 k6]]]' (DROID-SLAM), an "
                        "ORB-SLAM YAML or an OpenCV FileStorage YAML/XML (default: calib.txt beside the data)")
    p.add_argument("--viz", action="store_true", help="watch the run live in the rerun viewer (pvslam[viz])")
    p.add_argument("--viz-save", metavar="FILE.rrd", help="write the live view to a rerun recording file")


def _add_plugins(sub) -> None:
    p = sub.add_parser("plugins", help="list installed and catalogued plugins")
    p.add_argument("--json", action="store_true", help="machine-readable output")


def _add_config(sub) -> None:
    p = sub.add_parser("config", help="show or validate a configuration")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION")
    cs = csub.add_parser("show", help="print the resolved config (all defaults filled in) as a TOML config file")
    _add_config_args(cs)
    cs.add_argument("--json", action="store_true", help="print it as JSON (the run directory's config.json)")
    cv = csub.add_parser("validate", help="validate a config file; exit status 2 on errors")
    cv.add_argument("file", help="pipeline or ablation TOML")
    cv.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE")


def _add_synth(sub) -> None:
    p = sub.add_parser("synth", help="generate a built-in synthetic sequence with exact ground truth")
    p.add_argument("--scenario", default="driving_loop", help="scenario name (see --list)")
    p.add_argument("--list", action="store_true", help="list the scenarios")
    p.add_argument("--out", help="output folder (default: the cache folder used by `pvslam run`)")
    p.add_argument("--frames", type=int, help="number of frames (default: the scenario's)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--hfov", type=float, metavar="DEG", help="another camera: horizontal field of view in degrees "
                   "(default: the plugin's camera)")
    p.add_argument("--plugin", default="synthetic", help="dataset plugin that generates (default: synthetic)")


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="recompute the metrics of a run directory")
    p.add_argument("run_dir", help="a run directory written by `pvslam run`")


def _add_view(sub) -> None:
    p = sub.add_parser("view", help="replay a finished run in the rerun viewer (pvslam[viz])")
    p.add_argument("run_dir", help="a run directory written by `pvslam run`")
    p.add_argument("--save", metavar="FILE.rrd", help="write a rerun recording file instead of opening the viewer")
    p.add_argument("--spawn", action="store_true", help="with --save: also open the viewer")


def _add_export(sub) -> None:
    p = sub.add_parser("export", help="export a run for COLMAP / nerfstudio, or its trajectory aligned to the GT")
    p.add_argument("run_dir", help="a run directory written by `pvslam run`")
    from .outputs.formats import EXPORT_FORMATS

    p.add_argument("--format", "-f", required=True, choices=tuple(EXPORT_FORMATS),
                   help="; ".join(f"{f.name}: {f.help}" for f in EXPORT_FORMATS.values()))
    p.add_argument("--out", help="output folder (default: RUN_DIR/export/FORMAT)")
    p.add_argument("--no-images", action="store_true",
                   help="do not re-read the dataset to write the keyframe images")


def _add_train(sub) -> None:
    p = sub.add_parser("train", help="train a learned plugin (its registered trainer) on the built-in data")
    p.add_argument("interface", choices=("frontend", "segmenter", "loop", "vps"), help="which component")
    p.add_argument("--plugin", "-p", required=True, help="the plugin to train (see `pvslam plugins`)")
    p.add_argument("--config", "-c", metavar="FILE", help="training TOML (default: the trainer's defaults)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override one training parameter (repeatable)")
    p.add_argument("--out", help="output folder (default: runs/train-INTERFACE-PLUGIN-TIME)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")


def _add_weights(sub) -> None:
    p = sub.add_parser("weights", help="list, download (with checksum) and locate the learned plugins' checkpoints")
    wsub = p.add_subparsers(dest="weights_command", metavar="ACTION")
    wl = wsub.add_parser("list", help="catalogued checkpoints (registry.toml) and whether each is cached")
    wl.add_argument("--json", action="store_true", help="machine-readable output")
    wf = wsub.add_parser("fetch", help="download NAME into the cache and verify its checksum; prints the path")
    wf.add_argument("name", help="catalogue name or alias (see `pvslam weights list`)")
    wf.add_argument("--force", action="store_true", help="download again even when cached")
    wp = wsub.add_parser("path", help="print NAME's cache path (exit status 1 when it is not downloaded yet)")
    wp.add_argument("name", help="catalogue name or alias")


def _add_sweep(sub) -> None:
    p = sub.add_parser("sweep", help="run (or resume) a grid of sequences x seeds x variants, on Ray when installed")
    p.add_argument("--config", "-c", required=True, metavar="FILE", help="sweep TOML (see configs/sweep_table7.toml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override a base pipeline value for every cell, or a [sweep] value such as "
                        "sweep.seeds=[0] (repeatable)")
    p.add_argument("--output-dir", help="folder that holds sweep directories (overrides sweep.output_dir)")
    p.add_argument("--address", help="join this Ray cluster (e.g. auto or ray://host:10001) instead of a local one")
    p.add_argument("--workers", type=int, metavar="N", help="runs at a time (default: one per core)")
    p.add_argument("--serial", action="store_true", help="run the cells one after another in this process")
    p.add_argument("--retry-failed", action="store_true", help="run failed cells again (default: keep them)")
    p.add_argument("--report", action="store_true", help="only rebuild the results table and plots")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress display")


def _fail(msg: str, code: int) -> int:
    print(f"pvslam: error: {msg}", file=sys.stderr)
    return code


def _one_openmp_thread_by_default() -> None:
    """``OMP_NUM_THREADS=1`` unless the user set it, before torch / numpy / OpenCV load.  ``run.threads`` sets the
    pipeline thread's torch threads, but OpenMP's thread count is per thread: the reader, output and flow threads
    (pvslam_core/background.py, the flow frontend's lanes.py) started their own 2-thread OpenMP teams, which spun
    against the pipeline on a small machine (docs/decisions.md: OMP_NUM_THREADS)."""
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")


def main(argv: Optional[list[str]] = None) -> int:
    _one_openmp_thread_by_default()
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from importlib.metadata import version

        print(f"pvslam {version('pvslam')}")
        return 0
    if args.command is None:
        parser.print_help()
        return 0
    from .config import ConfigError
    from .registry import PluginError, PluginLoadWarning

    _plain_plugin_warnings(PluginLoadWarning)
    _console_notices()

    try:
        if args.command == "run":
            return _cmd_run(args)
        if args.command == "plugins":
            return _cmd_plugins(args)
        if args.command == "config":
            return _cmd_config(args, parser)
        if args.command == "synth":
            return _cmd_synth(args)
        if args.command == "eval":
            return _cmd_eval(args)
        if args.command == "view":
            return _cmd_view(args)
        if args.command == "export":
            return _cmd_export(args)
        if args.command == "train":
            return _cmd_train(args)
        if args.command == "weights":
            return _cmd_weights(args, parser)
        if args.command == "sweep":
            return _cmd_sweep(args)
    except (ConfigError, PluginError) as exc:
        return _fail(str(exc), EXIT_CONFIG)
    except KeyboardInterrupt:
        return _fail("interrupted; outputs written so far are kept", 130)
    except (FileNotFoundError, ValueError, RuntimeError, OSError) as exc:
        return _fail(f"{type(exc).__name__}: {exc}", EXIT_RUNTIME)
    return 0


def _plain_plugin_warnings(category: type) -> None:
    """Show a skipped plugin as one ``pvslam: warning: ...`` line instead of Python's warning with source line."""
    import warnings

    previous = warnings.showwarning

    def show(message, cat, filename, lineno, file=None, line=None):  # noqa: ANN001
        if issubclass(cat, category):
            print(f"pvslam: warning: {message}", file=sys.stderr)
        else:
            previous(message, cat, filename, lineno, file, line)

    if getattr(previous, "__name__", "") != "show":
        warnings.showwarning = show


# ------------------------------------------------------------------------------------------------ run --
def _run_overrides(args) -> list[str]:
    ov = list(args.overrides)
    if args.output_dir:
        ov.append(f"run.output_dir={json.dumps(args.output_dir)}")
    if args.name:
        ov.append(f"run.name={json.dumps(args.name)}")
    if args.quiet:
        ov.append("run.progress=false")
    return ov


def _cmd_run(args) -> int:
    from .api import path_overrides, run_ablation, run_config
    from .config import ConfigError, is_ablation_file
    from .report import comparison_table, summary_lines

    overrides = _run_overrides(args)
    if args.calib and not args.path:
        raise ConfigError("--calib goes with an input PATH (pvslam run PATH --calib FILE); in a config file set "
                          "dataset.calib")
    if args.config and is_ablation_file(args.config):
        if args.path or args.viz or args.viz_save:
            raise ConfigError("PATH, --viz and --viz-save apply to single runs, not to ablation files")
        results = run_ablation(args.config, overrides=overrides)
        print(comparison_table(results))
        failed = [n for n, r in results if r.metrics.get("failed")]
        if failed:
            return _fail(f"{len(failed)} of {len(results)} variants failed: {', '.join(failed)}", EXIT_RUNTIME)
        return 0
    if args.path:
        overrides, det = path_overrides(args.path, args.calib, overrides)
        print(f"pvslam: input: {det.description} ({det.plugin} reader)", file=sys.stderr)
    viewer = _viewer(spawn=args.viz, save=args.viz_save) if (args.viz or args.viz_save) else None
    try:
        result = run_config(args.config, overrides=overrides, observer=viewer)
    finally:
        if viewer is not None:
            viewer.close()
            if args.viz_save:
                print(f"pvslam: viewer recording: {args.viz_save} (open it with: rerun {args.viz_save})",
                      file=sys.stderr)
    for line in summary_lines(result):
        print(line)
    if result.metrics.get("tracking", {}).get("initialized") is False:
        return _fail("no motion was estimated: the map never initialised (too little parallax, too few frames or no "
                     "texture); trajectory.txt holds placeholder poses", EXIT_NO_MOTION)
    return 0


def _viewer(spawn: bool, save: Optional[str]):
    """The rerun viewer (a RunObserver); a missing rerun is a clear error, not a traceback."""
    try:
        from .viz.rerun_viewer import RerunViewer

        return RerunViewer(spawn=spawn, save=save)
    except ImportError as exc:
        raise RuntimeError(str(exc)) from None


def _cmd_view(args) -> int:
    from .viz.replay import replay_run

    viewer = _viewer(spawn=args.spawn or not args.save, save=args.save)
    try:
        summary = replay_run(args.run_dir, viewer)
    finally:
        viewer.close()
    missing = summary.pop("missing")
    print("replayed: " + ", ".join(f"{k} {v}" for k, v in summary.items()))
    if missing:
        print("not in the run directory: " + ", ".join(missing), file=sys.stderr)
    if args.save:
        print(f"recording: {args.save} (open it with: rerun {args.save})")
    return 0


class _StderrNotice(logging.StreamHandler):
    """Writes to the current ``sys.stderr`` (captured or redirected streams included)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr
        super().emit(record)


def _console_notices() -> None:
    """Choices the core makes for the user (``pvslam.notice``: e.g. no segmenter on unlabelled data) go to the
    console as ``pvslam: ...`` lines, besides log.txt."""
    log = logging.getLogger("pvslam.notice")
    if not any(isinstance(h, _StderrNotice) for h in log.handlers):
        h = _StderrNotice()
        h.setFormatter(logging.Formatter("pvslam: %(message)s"))
        log.addHandler(h)


def _cmd_plugins(args) -> int:
    from .catalog import load_catalog
    from .registry import INTERFACES, get_registry

    reg = get_registry()
    catalog = {(e.interface, e.name): e for e in load_catalog()}
    rows = []
    for interface in INTERFACES:
        names = set(reg.names(interface)) | {n for (i, n) in catalog if i == interface}
        for name in sorted(names):
            spec = reg.plugins.get((interface, name))
            entry = catalog.get((interface, name))
            rows.append({
                "interface": interface,
                "name": name,
                "state": "installed" if spec else (entry.status if entry else "?"),
                "version": spec.version if spec else "",
                "distribution": spec.distribution if spec else "",
                "description": (spec.description if spec and spec.description else (entry.description if entry else "")),
                "install": "" if spec else (entry.install if entry else ""),
                "needs_weights": bool(entry and entry.weights),
                "needs_gpu": bool(entry and entry.needs_gpu),
                "in_registry_toml": entry is not None,
            })
    broken = getattr(reg, "broken_entry_points", {})
    if args.json:
        # a broken entry point registered nothing, so its interface is unknown
        rows += [{"interface": None, "name": ep, "state": "broken", "error": why} for ep, why in broken.items()]
        print(json.dumps(rows, indent=2))
        return 0
    w_name = max(len(r["name"]) for r in rows)
    print(f"{'interface':<10} {'name':<{w_name}} {'state':<10} {'version':<8} description")
    for r in rows:
        extra = ""
        if r["state"] != "installed":
            extra = f"  [install: {r['install']}]"
        if r["needs_weights"]:
            extra += "  [needs weights]"
        print(f"{r['interface']:<10} {r['name']:<{w_name}} {r['state']:<10} {r['version']:<8} {r['description']}{extra}")
    if reg.skipped_entry_points:
        print("\nnot loaded (PVSLAM_LOAD_PLUGINS): " + ", ".join(reg.skipped_entry_points))
    if broken:
        print("\nbroken entry points (skipped):")
        for ep, why in broken.items():
            print(f"  {ep}: {why}")
    return 0


def _cmd_config(args, parser) -> int:
    from .config import is_ablation_file, load_ablation, load_config

    if args.config_command == "show":
        from .config_toml import to_toml

        if args.config and is_ablation_file(args.config):
            variants = load_ablation(args.config, overrides=args.overrides)
            if args.json:
                print(json.dumps({v.name: v.config.to_dict() for v in variants}, indent=2))
            for v in [] if args.json else variants:
                print(to_toml(v.config.to_dict(), f"variant {v.name!r}: resolved config"))
            return 0
        cfg = load_config(args.config, overrides=args.overrides)
        print(cfg.to_json() if args.json else to_toml(cfg.to_dict(), _SHOW_HEADER), end="" if not args.json else "\n")
        return 0
    if args.config_command == "validate":
        if is_ablation_file(args.file):
            variants = load_ablation(args.file, overrides=args.overrides)
            print(f"{args.file}: OK ({len(variants)} variants: {', '.join(v.name for v in variants)})")
        else:
            load_config(args.file, overrides=args.overrides)
            print(f"{args.file}: OK")
        return 0
    parser.parse_args(["config", "--help"])
    return 0


_SHOW_HEADER = "resolved config, every default filled in (a config file for --config; --json: as JSON)"


def _cmd_synth(args) -> int:
    from .registry import PluginError, get_registry

    spec = get_registry().get("dataset", args.plugin)
    if "generate" not in spec.extras:
        raise PluginError(f"dataset plugin {args.plugin!r} cannot generate sequences (it registers no `generate`)")
    generate, SCENARIOS = spec.extras["generate"], spec.extras.get("scenarios", {})
    if args.list:
        for name, desc in SCENARIOS.items():
            print(f"{name:<18} {desc}")
        return 0
    if args.scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {args.scenario!r}; available: {', '.join(SCENARIOS)}")
    camera = {} if args.hfov is None else {"hfov_deg": args.hfov}  # only asked of a generator when given
    out = generate(args.scenario, Path(args.out) if args.out else None, num_frames=args.frames,
                   width=args.width, height=args.height, seed=args.seed, progress=True, **camera)
    print(out)
    return 0


def _cmd_export(args) -> int:
    from .outputs.export import export_run

    summary = export_run(args.run_dir, args.format, args.out, images=not args.no_images)
    for k, v in summary.items():
        print(f"{k}: {v}")
    return 0


def _cmd_eval(args) -> int:
    from .api import evaluate_run_dir

    metrics = evaluate_run_dir(args.run_dir)
    for kind, src in metrics.get("evaluation_sources", {}).items():  # stderr: stdout stays pure JSON
        print(f"pvslam eval: {kind} ground truth: {src}" if kind != "dataset" else f"pvslam eval: dataset: {src}",
              file=sys.stderr)
    print(json.dumps(metrics, indent=2, default=float))
    return 0


def _cmd_sweep(args) -> int:
    from .sweep import run_sweep

    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {args.workers}")
    try:
        out = run_sweep(args.config, overrides=args.overrides, output_dir=args.output_dir, address=args.address,
                        workers=args.workers, serial=args.serial, retry_failed=args.retry_failed,
                        report_only=args.report, progress=not args.quiet)
    except KeyboardInterrupt:
        return _fail("sweep interrupted; finished cells are kept, run the same command again to resume", 130)
    if "summary_md" in out.tables:
        print(out.tables["summary_md"].read_text())
        print(f"per-cell table, CSV and plots: {out.tables['markdown'].parent}")
    print(f"sweep directory: {out.directory}  ({len(out.ran)} cells run, {len(out.skipped)} already finished, "
          f"{out.seconds:.1f} s)")
    if out.failed:
        return _fail(f"{len(out.failed)} cells failed (error.txt in each): " + ", ".join(sorted(out.failed)),
                     EXIT_RUNTIME)
    return 0


def _cmd_train(args) -> int:
    from .training import train

    out, summary = train(args.interface, args.plugin, args.config, args.overrides, args.out, args.resume)
    for k, v in summary.items():
        print(f"{k}: {v}")
    print(f"training folder: {out}")
    return 0


def _cmd_weights(args, parser) -> int:
    from . import weights as W

    if args.weights_command == "list":
        rows = []
        for w in W.catalog_weights():
            chk = W.expected_checksum(w)
            path = W.cached_path(w)
            rows.append({"name": w.name, "plugin": w.plugin, "used_by": w.used_by, "cached": path.is_file(),
                         "path": str(path), "checksum": chk.describe() if chk else "none (not verified)",
                         "manual": w.manual, "license": w.license, "url": w.url, "aliases": w.aliases})
        if args.json:
            print(json.dumps(rows, indent=2))
            return 0
        if not rows:
            print("registry.toml lists no weights")
            return 0
        wn = max(len(r["name"]) for r in rows)
        wp = max(len(r["plugin"]) for r in rows)
        print(f"{'name':<{wn}} {'plugin':<{wp}} {'state':<10} {'checksum':<25} licence")
        for r in rows:
            state = "cached" if r["cached"] else ("manual" if r["manual"] else "-")
            chk = r["checksum"].split(" (")[0]
            print(f"{r['name']:<{wn}} {r['plugin']:<{wp}} {state:<10} {chk:<25} {r['license']}")
        print(f"\ncache: {W.cache_dir()}  (PVSLAM_CACHE moves it)")
        return 0
    if args.weights_command == "fetch":
        path = W.fetch(args.name, force=args.force)
        print(path)
        return 0
    if args.weights_command == "path":
        path = W.cached_path(args.name)
        print(path)
        if not path.is_file():
            return _fail(f"{args.name!r} is not downloaded yet; run `pvslam weights fetch {args.name}`",
                         EXIT_RUNTIME)
        return 0
    parser.parse_args(["weights", "--help"])
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
