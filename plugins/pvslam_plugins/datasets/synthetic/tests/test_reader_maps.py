"""The ``synthetic`` reader decodes only the ground-truth maps it is asked for (``gt_maps``): by default the RGB image
and the panoptic labels; what it decodes equals what the full read gives."""
from __future__ import annotations

import numpy as np
import pytest

from pvslam_plugins.datasets.synthetic import generator
from pvslam_plugins.datasets.synthetic import reader as reader_mod
from pvslam_plugins.datasets.synthetic.config import SyntheticConfig
from pvslam_plugins.datasets.synthetic.reader import SyntheticReader, SyntheticSequence


@pytest.fixture(scope="module")
def seq_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("syn") / "mv"
    return generator.generate("moving_vehicles", root, num_frames=4, width=64, height=48, seed=3, progress=False)


def _read_dirs(monkeypatch, fn):
    """Run ``fn`` and return the folders of every image file it decoded."""
    seen = []
    orig = reader_mod.cv2.imread

    def spy(path, flags=None):
        seen.append(path.split("/")[-2])
        return orig(path, flags)

    monkeypatch.setattr(reader_mod.cv2, "imread", spy)
    out = fn()
    monkeypatch.setattr(reader_mod.cv2, "imread", orig)
    return out, seen


def test_default_reads_rgb_and_panoptic_only(seq_root, monkeypatch):
    r = SyntheticReader(SyntheticConfig(path=str(seq_root), crop_multiple=1))
    info = r.info()
    assert (info.has_gt_pose, info.has_gt_depth, info.has_gt_panoptic) == (True, False, True)
    frames, seen = _read_dirs(monkeypatch, lambda: list(r))
    assert sorted(set(seen)) == ["panoptic", "rgb"] and len(seen) == 2 * 4
    full = SyntheticSequence(seq_root)
    for f in frames:
        assert f.gt_depth is None and f.gt_dynamic is None
        ref = full.frame(f.index)  # every map
        assert bool((f.image == ref.image).all())
        assert bool((f.gt_panoptic.ids == ref.gt_panoptic.ids).all())
        assert f.gt_panoptic.segments == ref.gt_panoptic.segments
        assert bool((f.gt_pose == ref.gt_pose).all())


def test_each_map_on_request(seq_root, monkeypatch):
    full = SyntheticSequence(seq_root).arrays(2)
    for maps, dirs in ((["depth"], ["depth", "rgb"]), (["dynamic"], ["dynamic", "rgb"]), ([], ["rgb"]),
                       (["depth", "panoptic", "dynamic"], ["depth", "dynamic", "panoptic", "rgb"])):
        r = SyntheticReader(SyntheticConfig(path=str(seq_root), crop_multiple=1, gt_maps=maps))
        f, seen = _read_dirs(monkeypatch, lambda: r[2])
        assert sorted(seen) == dirs, maps
        assert (f.gt_depth is not None) == ("depth" in maps)
        assert (f.gt_dynamic is not None) == ("dynamic" in maps)
        assert (f.gt_panoptic is not None) == ("panoptic" in maps)
        if "depth" in maps:
            np.testing.assert_array_equal(f.gt_depth.numpy(), full["depth"])
        if "dynamic" in maps:
            np.testing.assert_array_equal(f.gt_dynamic.numpy(), full["dynamic"])


def test_unknown_map_is_a_config_error():
    with pytest.raises(ValueError, match="gt_maps"):
        SyntheticConfig(gt_maps=["normals"])
    with pytest.raises(ValueError, match="normals"):
        reader_mod._check_maps(["normals"])
