"""Seconds per frame of the built-in synthetic generator, per scenario and image size, on one core.

    python bench/bench_synth.py                      # 320x240 and 640x480, 20 frames each, render only
    python bench/bench_synth.py --write --frames 40  # also the full generate() (render + PNG/JSON writing)

Threads are pinned to one (OpenCV, BLAS/OpenMP) so the figures are per core.  ``cpu s/frame`` is the process CPU
time (robust on a busy machine); ``wall s/frame`` the elapsed time.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from pvslam_plugins.datasets.synthetic import generator, scenarios  # noqa: E402
from pvslam_plugins.datasets.synthetic.render import render  # noqa: E402
from pvslam_plugins.datasets.synthetic.textures import texture_atlas  # noqa: E402


def bench_render(name: str, width: int, height: int, frames: int) -> tuple[float, float, int]:
    sc = scenarios.build(name, width=width, height=height)
    idx = np.linspace(0, sc.num_frames - 1, frames).round().astype(int)
    render(sc.scene, int(idx[0]), sc.poses[idx[0]], sc.camera)  # warm-up
    c0, w0 = time.process_time(), time.perf_counter()
    for i in idx:
        render(sc.scene, int(i), sc.poses[i], sc.camera)
    return (time.process_time() - c0) / frames, (time.perf_counter() - w0) / frames, sc.num_frames


def bench_write(name: str, width: int, height: int, frames: int) -> tuple[float, float]:
    with tempfile.TemporaryDirectory() as d:
        c0, w0 = time.process_time(), time.perf_counter()
        generator.generate(name, Path(d) / name, num_frames=frames, width=width, height=height, progress=False)
        return (time.process_time() - c0) / frames, (time.perf_counter() - w0) / frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=20, help="frames timed per scenario and size")
    ap.add_argument("--sizes", default="320x240,640x480", help="comma-separated WxH")
    ap.add_argument("--scenarios", default=",".join(scenarios.SCENARIOS))
    ap.add_argument("--write", action="store_true", help="also time generate() with PNG/JSON writing")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    texture_atlas()
    print(f"texture atlas built in {time.perf_counter() - t0:.2f} s (once per process)")
    sizes = [tuple(int(x) for x in s.split("x")) for s in args.sizes.split(",")]
    header = f"{'scenario':<18} {'size':>9} {'default frames':>14} {'cpu s/frame':>12} {'wall s/frame':>13}"
    if args.write:
        header += f" {'generate cpu s/frame':>21} {'generate wall s/frame':>22}"
    print(header)
    print("-" * len(header))
    for name in args.scenarios.split(","):
        for w, h in sizes:
            cpu, wall, n = bench_render(name, w, h, args.frames)
            row = f"{name:<18} {f'{w}x{h}':>9} {n:>14} {cpu:>12.4f} {wall:>13.4f}"
            if args.write:
                gc, gw = bench_write(name, w, h, args.frames)
                row += f" {gc:>21.4f} {gw:>22.4f}"
            print(row, flush=True)


if __name__ == "__main__":
    main()
