"""domain.py: opt-in domain randomisation, its held-out split, and the plain generator left as it was."""
import dataclasses

import numpy as np
import pytest

from pvslam_plugins.datasets.synthetic import textures
from pvslam_plugins.datasets.synthetic.domain import (DOMAINS, HELD_OUT_FAMILIES, SIZE_RANGE, TEXTURE_FAMILIES,
                                                      TRAIN_FAMILIES, Look, family_textures)
from pvslam_plugins.datasets.synthetic.render import render
from pvslam_plugins.datasets.synthetic.scenarios import build

SCENARIOS = ("driving_loop", "moving_vehicles", "indoor_handheld", "handheld_fast", "indoor_textureless",
             "busy_street", "forward_low_parallax", "driving_city")


def _textures_used(scene) -> set[int]:
    """Every texture id of the scene's boxes, movers and of its ground over a 400 m square."""
    used = set(scene.static.tex.tolist())
    for m in scene.movers:
        used |= set(m.parts.tex.tolist())
    x, y = np.meshgrid(np.linspace(-200, 200, 161), np.linspace(-200, 200, 161))
    g = scene.ground(x.ravel(), y.ravel(), np.full(x.size, 0.01))
    return used | set(np.asarray(g.tex).tolist())


def test_families_partition_the_bank_and_the_split_is_disjoint():
    names = [n for f in TEXTURE_FAMILIES.values() for n in f]
    assert sorted(names) == sorted(textures.NAMES) and len(names) == len(set(names))
    assert set(HELD_OUT_FAMILIES).isdisjoint(TRAIN_FAMILIES) and len(HELD_OUT_FAMILIES) >= 2
    assert set(HELD_OUT_FAMILIES) | set(TRAIN_FAMILIES) == set(TEXTURE_FAMILIES)
    lo_train, hi_train = SIZE_RANGE["train"]
    assert SIZE_RANGE["heldout"][0] > hi_train > lo_train


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_no_training_scene_and_no_plain_scene_uses_a_held_out_family(scenario):
    held = set(family_textures(HELD_OUT_FAMILIES).tolist())
    for seed in (1, 17):
        assert not _textures_used(build(scenario, num_frames=2, seed=seed).scene) & held
        assert not _textures_used(build(scenario, num_frames=2, seed=seed, domain="train").scene) & held
    used = _textures_used(build(scenario, num_frames=2, seed=1, domain="heldout").scene)
    assert used <= held


def test_the_trainer_renders_its_randomised_frames_from_the_training_split(monkeypatch, tmp_path):
    from pvslam_plugins.segmenters.panoptic_fpn import data, train

    calls = []
    monkeypatch.setattr(data, "load_samples", lambda *a: calls.append(a) or [])
    cfg = train.TrainConfig(scenarios=["moving_vehicles"], domain_seeds=[11])
    train._samples(cfg, tmp_path, cfg.domain_seeds, 2, False, "", train.TRAINING_DOMAIN)
    assert calls and all(c[-1] == "train" for c in calls) and train.TRAINING_DOMAIN in DOMAINS
    assert train.TRAINING_DOMAIN != "heldout"
    with pytest.raises(ValueError, match="held out"):
        train.TrainConfig(domain_seeds=[100], val_seeds=[100, 101])


def test_held_out_things_are_larger_than_any_training_thing():
    plain = build("moving_vehicles", num_frames=2, seed=3).scene
    for domain in DOMAINS:
        lo, hi = SIZE_RANGE[domain]
        scene = build("moving_vehicles", num_frames=2, seed=3, domain=domain).scene
        assert len(scene.movers) == len(plain.movers) > 0
        for a, b in zip(plain.movers, scene.movers):
            length, height = b.size[0] / a.size[0], b.size[2] / a.size[2]
            assert lo <= length <= hi and lo <= height <= hi
            np.testing.assert_array_equal(a.poses, b.poses)  # the same paths


def test_randomised_frames_are_seeded_and_the_layout_and_labels_hold():
    a = build("indoor_handheld", num_frames=3, seed=5, domain="train")
    b = build("indoor_handheld", num_frames=3, seed=5, domain="train")
    c = build("indoor_handheld", num_frames=3, seed=6, domain="train")
    plain = build("indoor_handheld", num_frames=3, seed=5)
    ra, rb, rp = (render(s.scene, 1, s.poses[1], s.camera) for s in (a, b, plain))
    np.testing.assert_array_equal(ra.rgb, rb.rgb)
    assert not np.array_equal(ra.rgb, rp.rgb)
    assert set(np.unique(ra.panoptic)) == set(np.unique(rp.panoptic))  # same segments, other looks
    np.testing.assert_array_equal(a.poses, plain.poses)
    assert not np.array_equal(a.scene.static.tex, c.scene.static.tex)
    assert a.params["domain"] == "train" and "domain" not in plain.params and plain.scene.look is None
    with pytest.raises(ValueError, match="unknown domain 'test'"):
        build("indoor_handheld", num_frames=2, domain="test")


def test_look_hazes_with_depth_and_draws_its_noise_per_frame():
    col = np.full((4, 6, 3), 0.2, np.float32)
    depth = np.tile(np.array([0.0, 1.0, 10.0, 50.0, 100.0, 200.0], np.float32), (4, 1))
    look = Look(gain=1.0, gamma=1.0, white=(1.0, 1.0, 1.0), haze_per_m=0.05, haze_rgb=(0.8, 0.8, 0.8), blur_px=0.0,
                noise=0.0, seed=1)
    out = look(col, depth, 0)
    assert np.all(np.diff(out[0, 1:, 0]) > 0)  # farther: nearer the haze colour
    np.testing.assert_allclose(out[0, 0], 0.8)  # the sky takes the haze colour
    noisy = dataclasses.replace(look, noise=0.02)
    assert not np.array_equal(noisy(col, depth, 0), noisy(col, depth, 1))
    np.testing.assert_array_equal(noisy(col, depth, 3), noisy(col, depth, 3))


def test_generator_cache_keys_the_domain_and_leaves_plain_keys_alone(tmp_path, monkeypatch):
    from pvslam_plugins.datasets.synthetic.config import SyntheticConfig
    from pvslam_plugins.datasets.synthetic.generator import cache_path

    monkeypatch.setenv("PVSLAM_CACHE", str(tmp_path))
    plain = cache_path("moving_vehicles", seed=171)
    assert cache_path("moving_vehicles", seed=171, domain="heldout") != plain
    assert cache_path("moving_vehicles", seed=171, domain=None) == plain
    assert SyntheticConfig().domain is None
    with pytest.raises(ValueError):
        SyntheticConfig(domain="test")
