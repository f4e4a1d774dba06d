"""The colour preview of the panoptic output (the PNGs in panoptic/ hold ids, which look black in a viewer)."""
from __future__ import annotations

import cv2
import numpy as np
import torch

from pvslam_core.cli import main
from pvslam_core.outputs.panoptic_png import PanopticWriter
from pvslam_core.types import PanopticSegmentation, Segment


def test_run_panoptic_vis_writes_a_colour_preview_per_frame(fake_registry, fake_config_file, tmp_path, monkeypatch):
    from pvslam_core import registry as r

    monkeypatch.setattr(r, "_REGISTRY", fake_registry)
    assert main(["run", "-c", str(fake_config_file), "-q", "--panoptic-vis"]) == 0
    (run_dir,) = list((tmp_path / "runs").iterdir())
    ids = sorted(p.name for p in (run_dir / "panoptic").glob("*.png"))
    assert ids and sorted(p.name for p in (run_dir / "panoptic_vis").glob("*.png")) == ids
    img = cv2.imread(str(run_dir / "panoptic_vis" / ids[0]))
    assert img.shape[2] == 3 and len(np.unique(img.reshape(-1, 3), axis=0)) == 2  # the fake's two segments


def test_preview_without_declared_categories(tmp_path):
    """Without categories (a segmenter that declares none) the preview still comes, a stable colour per id."""
    ids = torch.ones(6, 8, dtype=torch.int64)
    ids[:, 4:] = 1002
    seg = PanopticSegmentation(ids, [Segment(1, 1, False), Segment(1002, 2, True)])
    with PanopticWriter(tmp_path, categories=None, vis=True, flush_every=0) as w:
        w.write(0, seg)
    img = cv2.imread(str(tmp_path / "panoptic_vis" / "000000.png"))
    assert img is not None and not np.array_equal(img[0, 0], img[0, 7]) and img.any()
