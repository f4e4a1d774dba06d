"""The ``pvslam`` command line.  Heavy libraries (torch, OpenCV, evo) are imported only inside commands, so
``pvslam --help`` answers at once."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

EXIT_CONFIG = 2
EXIT_RUNTIME = 1


def _add_config_args(p: argparse.ArgumentParser, required: bool = False) -> None:
    p.add_argument("--config", "-c", required=required, metavar="FILE",
                   help="pipeline TOML (or an ablation TOML with [[variant]] tables, or a run's config.json)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE",
                   help="override one config value, e.g. --set loop.plugin=none (repeatable; TOML value syntax)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pvslam",
        description="Panoptic visual SLAM: monocular video in; trajectory, depth/point cloud and temporally "
                    "consistent panoptic segmentation out.",
        epilog="Run with no config to process the built-in synthetic driving loop: pvslam run",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("run", help="run the pipeline (or every variant of an ablation file)")
    _add_config_args(p)
    p.add_argument("--output-dir", help="folder for run directories (overrides run.output_dir)")
    p.add_argument("--name", help="run name (overrides run.name)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar, only the summary")

    p = sub.add_parser("plugins", help="list installed and catalogued plugins")
    p.add_argument("--json", action="store_true", help="machine-readable output")

    p = sub.add_parser("config", help="show or validate a configuration")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION")
    cs = csub.add_parser("show", help="print the resolved config (all defaults filled in) as JSON")
    _add_config_args(cs)
    cv = csub.add_parser("validate", help="validate a config file; exit status 2 on errors")
    cv.add_argument("file", help="pipeline or ablation TOML")
    cv.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY.PATH=VALUE")

    p = sub.add_parser("synth", help="generate a built-in synthetic sequence with exact ground truth")
    p.add_argument("--scenario", default="driving_loop", help="scenario name (see --list)")
    p.add_argument("--list", action="store_true", help="list the scenarios")
    p.add_argument("--out", help="output folder (default: the cache folder used by `pvslam run`)")
    p.add_argument("--frames", type=int, help="number of frames (default: the scenario's)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--plugin", default="synthetic", help="dataset plugin that generates (default: synthetic)")

    p = sub.add_parser("eval", help="recompute the metrics of a run directory")
    p.add_argument("run_dir", help="a run directory written by `pvslam run`")
    return parser


def _fail(msg: str, code: int) -> int:
    print(f"pvslam: error: {msg}", file=sys.stderr)
    return code


def main(argv: Optional[list[str]] = None) -> int:
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
    from .registry import PluginError

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
    except (ConfigError, PluginError) as exc:
        return _fail(str(exc), EXIT_CONFIG)
    except KeyboardInterrupt:
        return _fail("interrupted; outputs written so far are kept", 130)
    except (FileNotFoundError, ValueError, RuntimeError, OSError) as exc:
        return _fail(f"{type(exc).__name__}: {exc}", EXIT_RUNTIME)
    return 0


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
    from .api import run_ablation, run_config
    from .config import is_ablation_file
    from .report import comparison_table, summary_lines

    overrides = _run_overrides(args)
    if args.config and is_ablation_file(args.config):
        results = run_ablation(args.config, overrides=overrides)
        print(comparison_table(results))
        return 0
    result = run_config(args.config, overrides=overrides)
    for line in summary_lines(result):
        print(line)
    return 0


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
    if args.json:
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
    return 0


def _cmd_config(args, parser) -> int:
    from .config import is_ablation_file, load_ablation, load_config

    if args.config_command == "show":
        if args.config and is_ablation_file(args.config):
            variants = load_ablation(args.config, overrides=args.overrides)
            print(json.dumps({v.name: v.config.to_dict() for v in variants}, indent=2))
        else:
            print(load_config(args.config, overrides=args.overrides).to_json())
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
    out = generate(args.scenario, Path(args.out) if args.out else None, num_frames=args.frames,
                   width=args.width, height=args.height, seed=args.seed, progress=True)
    print(out)
    return 0


def _cmd_eval(args) -> int:
    from .api import evaluate_run_dir

    metrics = evaluate_run_dir(args.run_dir)
    print(json.dumps(metrics, indent=2, default=float))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
