"""The shipped place-recognition checkpoints (``weights/deit_synth_{base,distilled}.pt``): they load strictly as the
default (``weights = "builtin"``) of their variant with the settings they were calibrated with, and retrieve a
revisit of a generated indoor room: a second view of the same place (0.18 m away, 5 degrees turned) ranks first,
well above four other places of the room, passes the geometric verification (the default), and is the only
candidate at the calibrated threshold."""
from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
import torch

from pvslam_core.types import Frame, Intrinsics
from pvslam_plugins.datasets.synthetic.render import render
from pvslam_plugins.datasets.synthetic.scenarios import build
from pvslam_plugins.loops.deit.checkpoint import load_checkpoint
from pvslam_plugins.loops.deit.config import DeitLoopConfig
from pvslam_plugins.loops.deit.descriptor import SHIPPED_SHA256, WEIGHTS_DIR, builtin_weights
from pvslam_plugins.loops.deit.detector import DeitLoopDetector

VARIANTS = ("base", "distilled")
ROOT = Path(__file__).resolve().parents[5]  # the repository (pyproject.toml)


def moved(T_wc: np.ndarray, right: float, forward: float, yaw_deg: float) -> np.ndarray:
    """``T_wc`` moved in its own frame (x right, z forward) and turned about its own y axis."""
    a = np.radians(yaw_deg)
    M = np.eye(4)
    M[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    M[0, 3], M[2, 3] = right, forward
    return T_wc @ M


@pytest.fixture(scope="module")
def revisit() -> list[Frame]:
    """Keyframes 0-5 of one generated room (indoor_handheld, seed 1, a world no checkpoint was trained or
    validated on): 0 = the pose of frame 10, 1-4 = frames at 20-65 % of the handheld loop (2-4.5 m away),
    5 = keyframe 0's place seen again, 0.18 m away and turned 5 degrees."""
    sc = build("indoor_handheld", seed=1)
    n = sc.num_frames
    poses = [sc.poses[10]] + [sc.poses[round(f * n)] for f in (0.2, 0.35, 0.5, 0.65)]
    poses.append(moved(sc.poses[10], 0.15, 0.1, 5.0))
    cam = sc.camera
    K = Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    frames = []
    for i, T in enumerate(poses):
        rgb = render(sc.scene, 0, T, cam).rgb  # uint8 [H, W, 3]
        frames.append(Frame(index=i, timestamp=float(i), image=torch.from_numpy(rgb).permute(2, 0, 1).contiguous(),
                            intrinsics=K))
    return frames


def detector(variant: str, **kw) -> DeitLoopDetector:
    """The shipped default of a variant, without the temporal exclusion (the keyframes here are seconds apart)."""
    return DeitLoopDetector(DeitLoopConfig(variant=variant, exclude_recent=0, min_time_gap=0.0, **kw))


@pytest.mark.parametrize("variant", VARIANTS)
def test_shipped_checkpoint_is_the_builtin_default(variant):
    path = builtin_weights(variant)
    assert path is not None and path == WEIGHTS_DIR / f"deit_synth_{variant}.pt", f"no shipped {variant} checkpoint"
    ck = load_checkpoint(path)  # strict: every key and shape of the stored architecture
    cfg = ck.model.config
    assert (cfg.embed_dim, cfg.depth, cfg.num_heads, cfg.patch_size) == (192, 4, 3, 16)
    assert cfg.distilled == (variant == "distilled")
    assert path.stat().st_size < 25e6  # the size limit
    det = DeitLoopDetector(DeitLoopConfig(variant=variant))  # weights = "builtin"
    assert det.trained and all(torch.equal(a, b) for a, b in zip(det.descriptor.model.state_dict().values(),
                                                                 ck.model.state_dict().values()))
    # the checkpoint's calibrated settings are the defaults; the geometric verification is on
    assert det.config.threshold == pytest.approx(ck.descriptor["threshold"])
    assert det.config.token == ck.descriptor["token"] and det.config.pca == ck.descriptor["pca"]
    assert tuple(det.config.input_size) == tuple(ck.descriptor["input_size"])
    assert det.config.verify and det.verifier is not None
    assert (det.retrieval.projector is None) == (ck.descriptor["pca"] == "none")


@pytest.mark.parametrize("variant", VARIANTS)
def test_shipped_checkpoint_retrieves_a_revisit(variant, revisit):
    # ranking: every place as a candidate (threshold -1); the revisit is first, far ahead of the others
    det = detector(variant, threshold=-1.0, max_candidates=10)
    for i, f in enumerate(revisit):
        det.add_keyframe(i, f)
    got = det.query(5)
    assert [c.j for c in got][:1] == [0], [(c.j, round(c.score, 3)) for c in got]
    best_other = max(c.score for c in got if c.j != 0)
    assert got[0].score - best_other > 0.25, [(c.j, round(c.score, 3)) for c in got]
    # the verification (ORB + essential matrix) accepts the revisit and rejects the other places
    assert {c.j for c in got if c.verified} == {0}
    # the shipped defaults (calibrated threshold, verification): exactly the revisit, verified
    det = detector(variant)
    for i, f in enumerate(revisit):
        det.add_keyframe(i, f)
    got = det.query(5)
    assert [(c.j, c.verified) for c in got] == [(0, True)], [(c.j, round(c.score, 3), c.verified) for c in got]


def test_readme_states_the_shipped_files():
    """weights/README.md documents exactly the shipped bytes (sha256 the loader checks) and how they were made."""
    text = (WEIGHTS_DIR / "README.md").read_text()
    for variant, digest in SHIPPED_SHA256.items():
        assert f"`deit_synth_{variant}.pt` | `{digest}`" in text, variant
    assert "pvslam train loop --plugin deit" in text and "101-108" in text and "201-202" in text


def test_checkpoints_are_package_data():
    """pyproject ships weights/*.pt with the package (an installed, non-editable pvslam has them too)."""
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert "weights/*.pt" in data.get("pvslam_plugins.loops.deit", [])
