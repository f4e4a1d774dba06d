"""Checkpoint loading: official layouts (152 / 155 keys, strict), key reports, variant detection, project format."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.loops.deit.checkpoint import (
    FORMAT,
    CheckpointError,
    compare_state_dict,
    detect_variant,
    infer_config,
    load_checkpoint,
    load_official,
    load_preset_weights,
    save_checkpoint,
)
from pvslam_plugins.loops.deit.pca import PCAWhitening
from pvslam_plugins.loops.deit.vit import (
    DistilledVisionTransformer,
    ViTConfig,
    VisionTransformer,
    deit_base_distilled_patch16_224,
    deit_base_patch16_224,
)


def official_layout(distilled: bool) -> dict[str, tuple[int, ...]]:
    """Key -> shape of the official DeiT-base checkpoints, written out from reference/checkpoints.md §1.2 (the
    table), independently of the model code."""
    D, L, C = 768, 12, 1000
    keys: dict[str, tuple[int, ...]] = {"cls_token": (1, 1, D), "pos_embed": (1, (2 if distilled else 1) + 196, D)}
    if distilled:
        keys["dist_token"] = (1, 1, D)
    keys["patch_embed.proj.weight"] = (D, 3, 16, 16)
    keys["patch_embed.proj.bias"] = (D,)
    for i in range(L):
        b = f"blocks.{i}."
        keys.update({b + "norm1.weight": (D,), b + "norm1.bias": (D,),
                     b + "attn.qkv.weight": (3 * D, D), b + "attn.qkv.bias": (3 * D,),
                     b + "attn.proj.weight": (D, D), b + "attn.proj.bias": (D,),
                     b + "norm2.weight": (D,), b + "norm2.bias": (D,),
                     b + "mlp.fc1.weight": (4 * D, D), b + "mlp.fc1.bias": (4 * D,),
                     b + "mlp.fc2.weight": (D, 4 * D), b + "mlp.fc2.bias": (D,)})
    keys.update({"norm.weight": (D,), "norm.bias": (D,), "head.weight": (C, D), "head.bias": (C,)})
    if distilled:
        keys.update({"head_dist.weight": (C, D), "head_dist.bias": (C,)})
    return keys


def synthetic_state_dict(layout: dict[str, tuple[int, ...]]) -> dict[str, torch.Tensor]:
    # zeros are cheap (87 M values); a few tensors get distinct values to check that they are really copied
    sd = {k: torch.zeros(s) for k, s in layout.items()}
    for n, k in enumerate(("cls_token", "blocks.11.mlp.fc2.bias", "head.bias")):
        sd[k] = torch.full(layout[k], float(n + 1))
    return sd


@pytest.mark.parametrize("distilled,n_keys,n_params", [(False, 152, 86_567_656), (True, 155, 87_338_192)])
def test_full_size_official_layout_loads_strictly(distilled, n_keys, n_params):
    layout = official_layout(distilled)
    assert len(layout) == n_keys
    assert sum(torch.Size(s).numel() for s in layout.values()) == n_params
    sd = synthetic_state_dict(layout)
    assert detect_variant(sd) == ("distilled" if distilled else "plain")
    cfg = infer_config(sd)
    assert (cfg.embed_dim, cfg.depth, cfg.num_heads, cfg.patch_size, cfg.img_size, cfg.num_classes, cfg.mlp_ratio) \
        == (768, 12, 12, 16, (224, 224), 1000, 4.0)
    # auto-detected from the 'model' entry of the official container
    m = load_official({"model": sd})
    assert isinstance(m, DistilledVisionTransformer if distilled else VisionTransformer)
    assert not m.training
    assert {k: tuple(v.shape) for k, v in m.state_dict().items()} == layout
    assert m.cls_token.eq(1).all() and m.blocks[11].mlp.fc2.bias.eq(2).all() and m.head.bias.eq(3).all()
    # the named presets expect exactly this layout too
    name = "deit_base_distilled_patch16_224" if distilled else "deit_base_patch16_224"
    m2 = load_preset_weights(name, sd)
    assert m2.head.bias.eq(3).all()
    with pytest.raises(CheckpointError, match="expected a plain DeiT" if distilled else "expected a distilled"):
        load_official({"model": sd}, expect_variant="plain" if distilled else "distilled")


def test_presets_have_the_documented_layout():
    for ctor, distilled in ((deit_base_patch16_224, False), (deit_base_distilled_patch16_224, True)):
        with torch.device("meta"):  # shapes only
            m = ctor()
        assert {k: tuple(v.shape) for k, v in m.state_dict().items()} == official_layout(distilled)
        assert all(mod.eps == 1e-6 for mod in m.modules() if isinstance(mod, torch.nn.LayerNorm))


def test_wrong_keys_give_a_full_report():
    layout = official_layout(False)
    sd = synthetic_state_dict(layout)
    del sd["blocks.3.attn.qkv.bias"]
    sd["blocks.12.norm1.weight"] = torch.zeros(768)  # a 13th block
    sd["head.weight"] = torch.zeros(10, 768)  # wrong class count
    with pytest.raises(CheckpointError) as ei:
        load_preset_weights("deit_base_patch16_224", {"model": sd})
    msg, rep = str(ei.value), ei.value.report
    assert rep is not None and not rep.ok
    assert rep.missing == [("blocks.3.attn.qkv.bias", (2304,))]
    assert rep.unexpected == [("blocks.12.norm1.weight", (768,))]
    assert rep.wrong_shape == [("head.weight", (1000, 768), (10, 768))]
    for part in ("missing (1)", "blocks.3.attn.qkv.bias  expected [2304]", "unexpected (1)",
                 "blocks.12.norm1.weight", "wrong shape (1)", "head.weight  expected [1000, 768], got [10, 768]"):
        assert part in msg, msg


def test_report_ok_and_not_a_vit():
    m = VisionTransformer(ViTConfig(img_size=32, embed_dim=16, depth=1, num_heads=2, num_classes=3))
    assert compare_state_dict(m, m.state_dict()).ok
    with pytest.raises(ValueError, match="needs DistilledVisionTransformer"):
        VisionTransformer(ViTConfig(img_size=32, embed_dim=16, depth=1, num_heads=2, distilled=True))
    with pytest.raises(CheckpointError, match="'cls_token' is missing"):
        load_official({"model": {"fc.weight": torch.zeros(2, 2)}})
    with pytest.raises(CheckpointError, match="not tensors"):
        load_official({"model": {"cls_token": torch.zeros(1), "epoch": 3}})


@pytest.fixture(scope="module")
def golden(fixtures_dir):
    return torch.load(fixtures_dir / "deit_vit_golden.pt", weights_only=True)


@pytest.mark.parametrize("which", ["plain", "distilled"])
@pytest.mark.parametrize("container", ["model", "bare", "module"])
def test_official_file_roundtrip(tmp_path, golden, which, container):
    """A file laid out like the official ones (reduced fixture weights) loads with weights_only and gives the
    golden outputs."""
    sd = golden[f"{which}_state_dict"]
    if container == "model":
        obj = {"model": sd, "epoch": 299}  # extra training entries are ignored
    elif container == "bare":
        obj = sd
    else:
        obj = {"model": {"module." + k: v for k, v in sd.items()}}  # DDP prefix stripped
    path = tmp_path / "deit.pth"
    torch.save(obj, path)
    m = load_official(path, num_heads=2)  # no shape shows the head count of the reduced model
    assert m.config.variant == which and m.config.embed_dim == 32 and m.config.num_classes == 10
    with torch.no_grad():
        out = m.forward_tokens(golden["x"])
    assert (out - golden[f"{which}_tokens_normed"]).abs().max() <= 1e-5


def test_project_checkpoint_roundtrip(tmp_path, golden):
    cfg = ViTConfig(img_size=64, embed_dim=32, depth=2, num_heads=2, num_classes=0, distilled=True,
                    pos_embed_antialias=False)
    m = DistilledVisionTransformer(cfg)
    sd = {k: v for k, v in golden["distilled_state_dict"].items() if not k.startswith("head")}
    m.load_state_dict(sd)
    pca = PCAWhitening.fit(torch.randn(50, 32, generator=torch.Generator().manual_seed(0)), dim=8)
    path = tmp_path / "sub" / "deit_small.pt"
    save_checkpoint(path, m, pca, descriptor={"token": "cls", "input_size": [64, 64]}, meta={"seed": 3})
    raw = torch.load(path, weights_only=True)  # plain types only
    assert raw["format"] == FORMAT and raw["variant"] == "distilled" and raw["config"]["num_heads"] == 2
    ck = load_checkpoint(path)
    assert ck.source_format == FORMAT and ck.meta == {"seed": 3} and ck.descriptor["token"] == "cls"
    assert ck.model.config.num_heads == 2 and ck.model.config.pos_embed_antialias is False
    assert isinstance(ck.model, DistilledVisionTransformer) and not ck.model.training
    x = torch.randn(4, 32)
    assert torch.allclose(ck.pca.transform(x), pca.transform(x))
    with torch.no_grad():
        assert torch.equal(ck.model.forward_tokens(golden["x"]), m.eval().forward_tokens(golden["x"]))

    bad = dict(raw, format_version=99)
    with pytest.raises(CheckpointError, match="format_version 99"):
        load_checkpoint(bad)
    bad = dict(raw, state_dict={k: v for k, v in raw["state_dict"].items() if k != "dist_token"})
    with pytest.raises(CheckpointError, match="missing \\(1\\):\n    dist_token"):
        load_checkpoint(bad)
    with pytest.raises(CheckpointError, match="unknown checkpoint format 'other'"):
        load_checkpoint({"format": "other"})
    # official files go through the same entry point
    ck2 = load_checkpoint({"model": golden["plain_state_dict"]}, num_heads=2)
    assert ck2.source_format == "official" and ck2.pca is None
