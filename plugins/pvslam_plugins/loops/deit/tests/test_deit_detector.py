"""The ``deit`` LoopDetector: stable ids and removal, batching, retrieval against a brute-force reference,
retrieval-only vs verified candidates, weights resolution and warnings, checkpoint settings, and a pipeline run."""
from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import skimage.data as skd
import torch

from pvslam_core.types import Frame, Intrinsics
from pvslam_plugins.loops.deit import descriptor as descriptor_mod
from pvslam_plugins.loops.deit.checkpoint import CheckpointError, save_checkpoint
from pvslam_plugins.loops.deit.config import DeitLoopConfig
from pvslam_plugins.loops.deit.detector import DeitLoopDetector, UntrainedDeitWarning, make_loop_detector
from pvslam_plugins.loops.deit.pca import PCAWhitening
from pvslam_plugins.loops.deit.preprocess import preprocess
from pvslam_plugins.loops.deit.vit import ViTConfig, build_vit

W, H = 320, 240
K = Intrinsics(fx=272.0, fy=272.0, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)
INPUT = (48, 64)


def _rgb(a: np.ndarray) -> np.ndarray:
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    return np.ascontiguousarray(a[..., :3])


PHOTOS = {n: _rgb(getattr(skd, n)()) for n in ("astronaut", "coffee", "rocket", "chelsea", "camera")}


def view(name: str, dx: int = 0, dy: int = 0, gain: float = 1.0) -> np.ndarray:
    a = PHOTOS[name]
    y0, x0 = (a.shape[0] - H) // 2 + dy, (a.shape[1] - W) // 2 + dx
    return np.clip(a[y0 : y0 + H, x0 : x0 + W].astype(np.float32) * gain, 0, 255).astype(np.uint8)


def noise_image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def frame(img: np.ndarray, index: int, t: float | None = None) -> Frame:
    return Frame(index=index, timestamp=float(index if t is None else t),
                 image=torch.from_numpy(img).permute(2, 0, 1).contiguous(), intrinsics=K)


@pytest.fixture(scope="module")
def tiny_model():
    torch.manual_seed(0)
    cfg = ViTConfig(img_size=INPUT, embed_dim=32, depth=2, num_heads=2, num_classes=0, distilled=True)
    return build_vit(cfg).eval()


@pytest.fixture
def tiny_weights(tmp_path, tiny_model):
    """A project checkpoint of a tiny distilled DeiT with stored descriptor settings (no PCA)."""
    path = tmp_path / "tiny.pt"
    save_checkpoint(path, tiny_model, None, {"input_size": list(INPUT), "pca": "none", "threshold": 0.5})
    return path


def cfg(weights, **kw) -> DeitLoopConfig:
    base = dict(weights=str(weights), variant="distilled", exclude_recent=1, min_time_gap=0.0, verify=False)
    base.update(kw)
    return DeitLoopConfig(**base)


def tour() -> list[np.ndarray]:
    return [view(n) for n in PHOTOS] + [noise_image(s) for s in range(3)]


# ------------------------------------------------------------------------------------------------------------
def test_candidates_match_a_brute_force_reference(tiny_weights, tiny_model):
    """Scores are cosines of L2(LN(cls)) of the full-frame input (computed here directly from the model);
    candidates are the older keyframes outside the exclusion with score >= threshold, best first, by id."""
    imgs = tour() + [view("coffee", dx=6, dy=-4), view("astronaut", dx=-5, dy=3, gain=1.1)]
    ids = [3 * k + 7 for k in range(len(imgs))]  # arbitrary increasing stable ids
    det = DeitLoopDetector(cfg(tiny_weights, threshold=-1.0, max_candidates=3, exclude_recent=2))
    assert det.config.input_size == INPUT and det.config.pca == "none"  # from the checkpoint
    for k, (i, img) in enumerate(zip(ids, imgs)):
        det.add_keyframe(i, frame(img, k))
    x = preprocess(torch.stack([frame(im, 0).image for im in imgs]), INPUT, "full_frame")
    with torch.no_grad():
        ref = torch.nn.functional.normalize(tiny_model.forward_tokens(x)[:, 0], dim=1)
    for q in range(len(imgs)):
        got = det.query(ids[q])
        sims = [(float(ref[q] @ ref[j]), ids[j]) for j in range(q - 2)]  # exclude_recent = 2
        want = sorted(sims, reverse=True)[:3]
        assert [c.j for c in got] == [j for _, j in want], q
        assert np.allclose([c.score for c in got], [s for s, _ in want], atol=1e-5)
        assert all(c.i == ids[q] and c.verified is None and c.inliers == 0 for c in got)  # retrieval only


def test_batched_descriptors_equal_one_by_one(tiny_weights):
    imgs = tour() + [view(n, dx=5, gain=0.9) for n in PHOTOS] + [noise_image(s) for s in (7, 8, 9)]  # no ties
    a = DeitLoopDetector(cfg(tiny_weights, batch_size=3, threshold=-1.0))
    b = DeitLoopDetector(cfg(tiny_weights, batch_size=1, threshold=-1.0))
    for k, img in enumerate(imgs):
        a.add_keyframe(k, frame(img, k))
    out_b = []
    for k, img in enumerate(imgs):
        b.add_keyframe(k, frame(img, k))
        out_b.append(b.query(k))
    out_a = [a.query(k) for k in range(len(imgs))]
    assert a.forward_batches == [3, 3, 3, 3, 3, 1] and b.forward_batches == [1] * len(imgs)
    assert torch.allclose(a.descriptors(), b.descriptors(), atol=1e-5)
    for ca, cb in zip(out_a, out_b):
        assert [c.j for c in ca] == [c.j for c in cb]
        assert np.allclose([c.score for c in ca], [c.score for c in cb], atol=1e-5)


def test_ids_removal_and_order(tiny_weights):
    det = DeitLoopDetector(cfg(tiny_weights, threshold=-1.0, max_candidates=10, batch_size=4))
    imgs = tour()
    for k, img in enumerate(imgs[:7]):
        det.add_keyframe(10 * k, frame(img, k))
    assert det.forward_batches == [4]  # 0..30 described, 40..60 still buffered
    det.on_keyframe_removed(10)  # a described keyframe
    det.on_keyframe_removed(60)  # a buffered one
    det.on_keyframe_removed(999)  # unknown ids are ignored
    det.add_keyframe(70, frame(imgs[7], 7))
    assert det.keyframe_ids() == [0, 20, 30, 40, 50, 70]
    got = det.query(70)
    # never a removed id; 50 is the newest older keyframe, inside the exclusion (exclude_recent = 1, by position
    # among the keyframes still stored: the removal of 60 made 50 the neighbour of 70)
    assert sorted(c.j for c in got) == [0, 20, 30, 40]
    with pytest.raises(KeyError, match="keyframe id 60"):
        det.query(60)
    with pytest.raises(ValueError, match="time order"):
        det.add_keyframe(65, frame(imgs[0], 99))
    # removal after description keeps the other descriptors in place (row shifts are internal)
    before = {i: d for i, d in zip(det.keyframe_ids(), det.descriptors())}
    det.on_keyframe_removed(30)
    after = {i: d for i, d in zip(det.keyframe_ids(), det.descriptors())}
    assert sorted(after) == [0, 20, 40, 50, 70] and all(torch.equal(after[i], before[i]) for i in after)


def test_verification_path_and_skip(tiny_weights):
    """verify = true: candidates go through the shared ORB + essential-matrix check (True for the revisit, False
    for the other places); the policy's skip predicate spares verifications; ids stay stable."""
    det = DeitLoopDetector(cfg(tiny_weights, threshold=-1.0, max_candidates=20, verify=True, min_inliers=30,
                               min_inlier_ratio=0.3))
    imgs = tour()
    for k, img in enumerate(imgs):
        det.add_keyframe(100 + k, frame(img, k))
    q = 100 + len(imgs)
    det.add_keyframe(q, frame(view("rocket", dx=8, dy=-5, gain=0.9), len(imgs)))
    out = det.query(q)
    assert len(out) == len(imgs) - 1  # all but the excluded newest one
    assert [c.j for c in out if c.verified] == [102]  # "rocket"
    assert all(c.verified is False for c in out if c.j != 102)
    good = next(c for c in out if c.j == 102)
    assert good.inliers >= 30
    assert len(det.last_verifications) == len(out)
    det.query(q, skip=lambda j: j != 102)
    assert [v[1] for v in det.last_verifications] == [102]
    det.on_keyframe_removed(102)
    assert all(c.verified is not True for c in det.query(q))


def test_checkpoint_settings_yield_to_explicit_config(tiny_weights):
    det = DeitLoopDetector(cfg(tiny_weights))
    assert det.config.threshold == 0.5 and det.trained
    det = DeitLoopDetector(cfg(tiny_weights, threshold=0.9, input_size=(32, 48)))
    assert det.config.threshold == 0.9 and det.config.input_size == (32, 48)
    with pytest.raises(ValueError, match="asks for plain"):
        DeitLoopDetector(cfg(tiny_weights, variant="base"))
    with pytest.raises(Exception, match="no such file"):
        DeitLoopDetector(cfg("/nonexistent/deit.pt"))


def test_pca_from_checkpoint(tmp_path, tiny_model):
    feats = torch.randn(50, 32, generator=torch.Generator().manual_seed(1))
    pca = PCAWhitening.fit(feats, dim=8, whiten=False)
    path = tmp_path / "with_pca.pt"
    save_checkpoint(path, tiny_model, pca, {"input_size": list(INPUT), "pca": "fixed", "threshold": 0.3})
    det = DeitLoopDetector(cfg(path))
    assert det.retrieval.projector is det.checkpoint.pca
    det.add_keyframe(0, frame(view("coffee"), 0))
    assert det.descriptors().shape == (1, 8)


def test_untrained_warns_and_builtin_default(tmp_path, monkeypatch, tiny_model):
    """weights = None / 'none': a random full-size DeiT (replaced by a tiny one here to stay fast) and a loud
    warning. 'builtin' (the default) is the shipped checkpoint of the variant, checked: missing or not the shipped
    bytes (sha256) is an error naming the file, never a silent fallback to random weights."""
    made = []

    def tiny(**kw):
        made.append(kw)
        return build_vit(ViTConfig(img_size=INPUT, embed_dim=32, depth=1, num_heads=2, num_classes=0,
                                   distilled=True))

    monkeypatch.setattr(descriptor_mod, "deit_base_distilled_patch16_224", tiny)
    for weights in (None, "none"):
        with pytest.warns(UntrainedDeitWarning, match="MEANINGLESS"):
            det = DeitLoopDetector(DeitLoopConfig(weights=weights, input_size=INPUT))
        assert not det.trained
    assert len(made) == 2
    # missing shipped file
    monkeypatch.setattr(descriptor_mod, "WEIGHTS_DIR", tmp_path / "none_here")
    with pytest.raises(FileNotFoundError, match=r"none_here.deit_synth_distilled\.pt is missing"):
        DeitLoopDetector(DeitLoopConfig(input_size=INPUT))
    # a file that is not the shipped one (the real hashes are expected): corrupt; a Git LFS pointer is named
    shipped = tmp_path / "shipped"
    save_checkpoint(shipped / "deit_synth_distilled.pt", tiny_model, None, {"threshold": 0.42})
    monkeypatch.setattr(descriptor_mod, "WEIGHTS_DIR", shipped)
    with pytest.raises(CheckpointError, match=r"deit_synth_distilled\.pt is corrupt or was replaced"):
        DeitLoopDetector(DeitLoopConfig(input_size=INPUT))
    lfs = tmp_path / "lfs"
    lfs.mkdir()
    (lfs / "deit_synth_distilled.pt").write_text("version https://git-lfs.github.com/spec/v1\noid sha256:0c0e\n")
    monkeypatch.setattr(descriptor_mod, "WEIGHTS_DIR", lfs)
    with pytest.raises(CheckpointError, match="git lfs pull"):
        DeitLoopDetector(DeitLoopConfig(input_size=INPUT))
    # the registered hash matches: loaded, with its stored threshold, no warning, no random model
    digest = hashlib.sha256((shipped / "deit_synth_distilled.pt").read_bytes()).hexdigest()
    monkeypatch.setattr(descriptor_mod, "WEIGHTS_DIR", shipped)
    monkeypatch.setitem(descriptor_mod.SHIPPED_SHA256, "distilled", digest)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UntrainedDeitWarning)
        det = make_loop_detector(DeitLoopConfig(input_size=INPUT), None)
    assert det.trained and det.config.threshold == 0.42 and len(made) == 2


def test_registered_with_trainer():
    import pvslam_plugins.loops.deit as plugin

    got = {}

    def register(name, factory, model, description="", **extras):
        got.update(name=name, factory=factory, model=model, extras=extras)

    plugin.register_loop_detectors(register=register)
    assert got["name"] == "deit" and got["model"] is DeitLoopConfig
    assert got["extras"]["trainer"].config_model.__name__ == "DeitTrainConfig"
    with pytest.raises(Exception):
        DeitLoopConfig(consecutive=3)  # the loop policy's rule, not the detector's
    assert DeitLoopConfig(variant="deit-base-distilled").variant == "distilled"  # upstream names accepted


@pytest.mark.slow
def test_pipeline_run_with_deit(tmp_path, tiny_weights):
    """A short pipeline run with loop.plugin = "deit" completes; with a permissive retrieval-only setting its
    candidates reach the loop policy (accept_unverified) and close loops."""
    from pvslam_core.api import run_config
    from pvslam_plugins.datasets.synthetic.generator import generate

    seq = generate("driving_loop", None, num_frames=40, progress=False)
    res = run_config(None, overrides=[
        f'run.output_dir="{(tmp_path / "runs").as_posix()}"', "run.progress=false", f'dataset.path="{seq.as_posix()}"',
        'loop.plugin="deit"', f'loop.weights="{tiny_weights.as_posix()}"', "loop.threshold=-1.0",
        "loop.exclude_recent=2", "loop.min_time_gap=0.0", "loop.verify=false", "outputs.ply=false",
        'vps.plugin="none"'])
    d = Path(res.run_dir)
    assert (d / "trajectory.txt").is_file() and json.loads((d / "metrics.json").read_text())["timing"]["frames"] == 40
    assert res.loops and all(c.verified is None for c in res.loops)
