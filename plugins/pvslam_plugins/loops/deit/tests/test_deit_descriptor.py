"""Preprocessing (against PIL), token selection (against the golden DeiT outputs), batched descriptors, model setup."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from pvslam_plugins.loops.deit.checkpoint import save_checkpoint
from pvslam_plugins.loops.deit.config import DeitDescriptorConfig, DeitModelConfig
from pvslam_plugins.loops.deit.descriptor import DeitDescriptor, build_model, make_projector, select_tokens
from pvslam_plugins.loops.deit.pca import OnlinePCA, PCAWhitening
from pvslam_plugins.loops.deit.preprocess import IMAGENET_MEAN, IMAGENET_STD, full_frame_size, preprocess
from pvslam_plugins.loops.deit.vit import DistilledVisionTransformer, ViTConfig, VisionTransformer


def smooth_image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """uint8 [h, w, 3] with structure at several scales (so resampling filters matter)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.zeros((h, w, 3), np.float32)
    for f in (3.0, 11.0, 29.0):
        ph = rng.uniform(0, 2 * np.pi, 3)
        img += np.sin(xx[..., None] / f + ph) * np.cos(yy[..., None] / (0.7 * f) + ph[::-1])
    img += rng.normal(0, 0.3, img.shape)
    return np.clip(127.5 + 40 * img, 0, 255).astype(np.uint8)


def to_chw(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(a).permute(2, 0, 1).contiguous()


def _pil_close(got: torch.Tensor, ref: torch.Tensor) -> None:
    """PIL rounds to uint8 after each of its two separable passes (measured here: <= 1.5/255, mean 0.3/255);
    plain bicubic (a = -0.75) is off by >= 5/255 (max) / 0.8/255 (mean), bilinear by ~10/255 / 1.7/255."""
    d = (got - ref).abs()
    assert d.max() <= 1.6 / 255 and d.mean() <= 0.4 / 255, (d.max() * 255, d.mean() * 255)


@pytest.mark.parametrize("size", [224, 112])
def test_center_crop_matches_the_pil_eval_transform(size):
    """DeiT eval: Resize(int(size / 0.875), PIL bicubic) on the shorter side, CenterCrop(size) (torchvision's
    rounding), written here with PIL directly."""
    img = smooth_image(150, 200)
    short = int(size / 0.875)
    rw, rh = int(short * 200 / 150), short
    ref = np.asarray(Image.fromarray(img).resize((rw, rh), Image.BICUBIC), np.float32) / 255.0
    top, left = int(round((rh - size) / 2.0)), int(round((rw - size) / 2.0))
    ref = torch.from_numpy(ref[top : top + size, left : left + size]).permute(2, 0, 1)
    got = preprocess(to_chw(img), size, "center_crop", mean=(0, 0, 0), std=(1, 1, 1))[0]
    assert got.shape == (3, size, size)
    _pil_close(got, ref)
    # normalisation
    norm = preprocess(to_chw(img), size, "center_crop")[0]
    m, s = torch.tensor(IMAGENET_MEAN).view(3, 1, 1), torch.tensor(IMAGENET_STD).view(3, 1, 1)
    assert torch.allclose(norm, (got - m) / s, atol=1e-6)


def test_full_frame_sizes_and_content():
    assert full_frame_size(376, 1241, 224) == (128, 384)  # KITTI: 8 x 24 patches ~ the 196 of 224 x 224
    assert full_frame_size(480, 640, 224) == (192, 256)  # 12 x 16 = 192 patches
    assert full_frame_size(480, 640, 112) == (96, 128)
    assert full_frame_size(480, 640, (64, 96)) == (64, 96)
    with pytest.raises(ValueError, match="multiples of the patch size"):
        full_frame_size(480, 640, (60, 96))
    # full frame: a PIL bicubic resize of the whole image (nothing cropped)
    img = smooth_image(120, 160, seed=1)
    ref = torch.from_numpy(np.asarray(Image.fromarray(img).resize((128, 96), Image.BICUBIC), np.float32) / 255.0)
    got = preprocess(to_chw(img), (96, 128), "full_frame", mean=(0, 0, 0), std=(1, 1, 1))[0]
    _pil_close(got, ref.permute(2, 0, 1))
    # batches, lists and float input agree
    b = torch.stack([to_chw(img), to_chw(smooth_image(120, 160, seed=2))])
    x1 = preprocess(b, 112)
    x2 = preprocess([b[0], b[1]], 112)
    x3 = preprocess(b.float() / 255, 112)
    assert x1.shape == (2, 3, 96, 128) and torch.equal(x1, x2) and torch.allclose(x1, x3, atol=1e-6)
    with pytest.raises(ValueError, match="different input sizes"):
        preprocess([b[0], b[0, :, :60]], 112)


@pytest.fixture(scope="module")
def golden(fixtures_dir):
    return torch.load(fixtures_dir / "deit_vit_golden.pt", weights_only=True)


def _small(golden, distilled: bool) -> VisionTransformer:
    cfg = ViTConfig(img_size=64, embed_dim=32, depth=2, num_heads=2, num_classes=10, distilled=distilled)
    m = DistilledVisionTransformer(cfg) if distilled else VisionTransformer(cfg)
    m.load_state_dict(golden["distilled_state_dict" if distilled else "plain_state_dict"])
    return m.eval()


def test_select_tokens_against_golden(golden):
    t = golden["distilled_tokens_normed"]
    cls, dist = golden["distilled_features_cls"], golden["distilled_features_dist"]
    assert torch.allclose(select_tokens(t, "cls", 2), cls, atol=1e-6)
    assert torch.allclose(select_tokens(t, "dist", 2), dist, atol=1e-6)
    assert torch.allclose(select_tokens(t, "mean", 2), (cls + dist) / 2, atol=1e-6)
    assert torch.allclose(select_tokens(t, "concat", 2), torch.cat([cls, dist], 1), atol=1e-6)
    assert torch.allclose(select_tokens(golden["plain_tokens_normed"], "cls", 1), golden["plain_features"])
    with pytest.raises(ValueError, match="needs the distilled model"):
        select_tokens(golden["plain_tokens_normed"], "dist", 1)


def test_descriptor_features_batched_and_equal_to_the_model(golden):
    m = _small(golden, distilled=True)
    imgs = torch.stack([to_chw(smooth_image(48, 80, seed=s)) for s in range(5)])
    cfg = DeitDescriptorConfig(input_size=(48, 80), token="concat", batch_size=2)
    desc = DeitDescriptor(m, cfg)
    assert desc.feature_dim == 64 and desc.input_size(48, 80) == (48, 80)
    f = desc.features(imgs)
    assert f.shape == (5, 64) and f.dtype == torch.float32
    with torch.no_grad():
        cls, dist = m.forward_features(preprocess(imgs, (48, 80)))
    assert torch.allclose(f, torch.cat([cls, dist], 1), atol=1e-5)
    # batch composition does not change a keyframe's descriptor
    one = DeitDescriptor(m, DeitDescriptorConfig(input_size=(48, 80), token="concat", batch_size=1)).features(imgs)
    assert torch.allclose(one, f, atol=1e-5)
    # describe: unit norm, with or without a projector
    u = desc.describe(imgs)
    assert torch.allclose(u.norm(dim=1), torch.ones(5), atol=1e-5)
    pca = PCAWhitening.fit(f, dim=3)
    up = desc.describe(imgs, pca)
    assert up.shape == (5, 3) and torch.allclose(up.norm(dim=1), torch.ones(5), atol=1e-5)
    # the model is left in the mode it was in
    m.train()
    desc.features(imgs[:1])
    assert m.training
    with pytest.raises(ValueError, match="needs the distilled model"):
        DeitDescriptor(_small(golden, distilled=False), DeitDescriptorConfig(token="dist"))


def test_build_model_and_projector(tmp_path, golden):
    m = _small(golden, distilled=True)
    pca = PCAWhitening.fit(torch.randn(40, 32, generator=torch.Generator().manual_seed(0)), dim=6)
    path = tmp_path / "w.pt"
    save_checkpoint(path, m, pca)
    model, ck = build_model(DeitModelConfig(variant="deit-base-distilled", weights=str(path),
                                            pos_embed_antialias=False))
    assert ck is not None and ck.pca is not None and model.config.pos_embed_antialias is False
    with pytest.raises(ValueError, match="asks for plain"):
        build_model(DeitModelConfig(variant="deit-base", weights=str(path)))
    assert make_projector(DeitDescriptorConfig(pca="none")) is None
    online = make_projector(DeitDescriptorConfig(pca="online", pca_dim=8, pca_min_samples=4))
    assert isinstance(online, OnlinePCA) and online.dim == 8 and online.min_samples == 4
    assert make_projector(DeitDescriptorConfig(pca="fixed"), ck.pca) is ck.pca
    pca.save(tmp_path / "p.pt")
    loaded = make_projector(DeitDescriptorConfig(pca="fixed", pca_file=str(tmp_path / "p.pt")))
    assert isinstance(loaded, PCAWhitening) and loaded.out_dim == 6
    with pytest.raises(ValueError, match="pca='fixed' needs"):
        make_projector(DeitDescriptorConfig(pca="fixed"))


def test_config_is_strict():
    with pytest.raises(ValueError):
        DeitDescriptorConfig(tokn="cls")
    with pytest.raises(ValueError):
        DeitDescriptorConfig(input_size=8)
    with pytest.raises(ValueError):
        DeitDescriptorConfig(token="both")
