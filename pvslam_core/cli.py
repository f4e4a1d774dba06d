"""The ``pvslam`` command line.  Heavy libraries (torch, OpenCV, evo) are imported only inside commands, so
``pvslam --help`` answers at once."""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Optional

from .cli_parser import build_parser  # the arguments, one function per command

EXIT_CONFIG = 2
EXIT_RUNTIME = 1
EXIT_NO_MOTION = 3  # the run finished but estimated no motion


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
    except Exception as exc:
        if not _is_opencv_error(exc):
            raise
        return _fail(_opencv_message(exc), EXIT_RUNTIME)
    return 0


def _is_opencv_error(exc: BaseException) -> bool:
    """Whether ``exc`` is OpenCV's ``cv2.error`` (without importing OpenCV where no command did)."""
    cv2 = sys.modules.get("cv2")
    return cv2 is not None and isinstance(exc, getattr(cv2, "error", ()))


def _opencv_message(exc: BaseException) -> str:
    """One line: where the run stopped (the stage and the frame, see pipeline.failed_at) and OpenCV's assertion."""
    from .pipeline import failed_at

    what = (getattr(exc, "err", "") or next((ln for ln in str(exc).splitlines() if ln.strip()), "")).strip()
    func = getattr(exc, "func", "")
    where = failed_at(exc)
    msg = f"OpenCV error{f' in {where}' if where else ''}: {what}{f' (in {func})' if func else ''}"
    kept = where and not getattr(exc, "pvslam_run_dir_removed", False)
    return msg + ("; the run directory keeps what was written" if kept else "")


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
    # as (key, value) pairs, not as TOML text: a name or path holds any character (an emoji, a backslash)
    if args.output_dir:
        ov.append(("run.output_dir", args.output_dir))
    if args.name:
        ov.append(("run.name", args.name))
    if args.quiet:
        ov.append("run.progress=false")
    if args.panoptic_vis:
        ov.append(("outputs.panoptic_vis", True))
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
        overrides, det = path_overrides(args.path, args.calib, overrides, config=args.config)
        print(f"pvslam: input: {det.description} ({det.plugin} reader)", file=sys.stderr)
    viewer = (_viewer(spawn=args.viz, save=args.viz_save, hint="pvslam run ... --viz-save FILE.rrd")
              if (args.viz or args.viz_save) else None)
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


def _viewer(spawn: bool, save: Optional[str], hint: str):
    """The rerun viewer (a RunObserver); a missing rerun or no display is a clear error, not a traceback or a
    wait; ``hint``: the command that records the view to a file instead."""
    from .config import ConfigError
    from .viz import ViewerUnavailable

    try:
        from .viz.rerun_viewer import RerunViewer

        return RerunViewer(spawn=spawn, save=save)
    except ImportError as exc:
        raise RuntimeError(str(exc)) from None
    except ViewerUnavailable as exc:
        raise ConfigError(f"{exc}; record the view to a file instead: {hint}, then open it where there is a "
                          "display with: rerun FILE.rrd") from None


def _cmd_view(args) -> int:
    from .viz.replay import replay_run

    viewer = _viewer(spawn=args.spawn or not args.save, save=args.save,
                     hint=f"pvslam view {args.run_dir} --save FILE.rrd")
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

    metrics = evaluate_run_dir(args.run_dir, gt=args.gt)
    for kind, src in metrics.get("evaluation_sources", {}).items():  # stderr: stdout stays pure JSON
        print(f"pvslam eval: {kind} ground truth: {src}" if kind != "dataset" else f"pvslam eval: dataset: {src}",
              file=sys.stderr)
    from .report import metric_lines

    for line in metric_lines({k: v for k, v in metrics.items() if k != "timing"}, args.run_dir):
        print(f"pvslam eval: {line}", file=sys.stderr)
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
