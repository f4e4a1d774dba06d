"""The arguments of the ``pvslam`` command line, one function per command (:mod:`pvslam_core.cli` runs them).
Nothing heavy is imported here: ``pvslam --help`` answers at once."""
from __future__ import annotations

import argparse


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
    p.add_argument("--panoptic-vis", action="store_true",
                   help="also write a colour preview of each panoptic PNG to panoptic_vis/ (the PNGs in panoptic/ "
                        "hold ids; sets outputs.panoptic_vis)")
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
    p.add_argument("--gt", metavar="FILE", help="ground-truth trajectory of the run's input: TUM (timestamp tx ty tz "
                   "qx qy qz qw, matched by timestamp) or KITTI poses (3x4 per line, one per input frame); becomes the "
                   "run's groundtruth.txt")


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
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint, with "
                   "its saved configuration (--config / --set change single keys of it)")


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
