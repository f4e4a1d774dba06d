"""Tiny sweep grids on short, low-resolution built-in scenarios (a cell takes a few seconds on 2 cores)."""
from __future__ import annotations

import textwrap
from pathlib import Path

FRAMES, WIDTH, HEIGHT = 36, 160, 120  # ~5 keyframes... enough for the map to initialise and ATE to be defined


def sweep_text(out: Path, *, scenarios=("driving_loop",), seeds=(0,), extra_sequences: str = "",
               variants: str = "", name: str = "tiny", panoptic: bool = True) -> str:
    variants = variants or textwrap.dedent('''
        [[variant]]
        name = "online_ba+loop"

        [[variant]]
        name = "offline_ba"
        "optimizer.plugin" = "offline_ba"
        "loop.plugin" = "none"
        ''')
    vps = "" if panoptic else '[vps]\nplugin = "none"\n'
    return textwrap.dedent(f'''
        [sweep]
        name = "{name}"
        output_dir = "{out.as_posix()}"
        scenarios = {list(scenarios)!r}
        seeds = {list(seeds)!r}
        scenario_params = {{ num_frames = {FRAMES}, width = {WIDTH}, height = {HEIGHT} }}
        plots = true

        [segmenter]
        plugin = "labels"

        [outputs]
        ply = false
        panoptic_png = {str(panoptic).lower()}
        plots = false

        [graph.init]
        warmup = 3
        ''') + vps + extra_sequences + variants


