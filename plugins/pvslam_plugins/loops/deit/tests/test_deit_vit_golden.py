"""Every tensor of ``deit_vit_golden.pt`` (timm-0.3.3 ViT / DeiT distilled / timm resample) reproduced to <= 1e-5."""
from __future__ import annotations

import pytest
import torch

from pvslam_plugins.loops.deit.vit import (
    DistilledVisionTransformer,
    ViTConfig,
    VisionTransformer,
    resample_abs_pos_embed,
)

TOL = 1e-5


@pytest.fixture(scope="module")
def golden(fixtures_dir):
    return torch.load(fixtures_dir / "deit_vit_golden.pt", weights_only=True)


def _config(golden) -> ViTConfig:
    c = golden["meta"]["config"]
    assert c["layernorm_eps"] == 1e-6 and c["qkv_bias"] and c["mlp_ratio"] == 4
    return ViTConfig(img_size=c["img_size"], patch_size=c["patch_size"], embed_dim=c["embed_dim"], depth=c["depth"],
                     num_heads=c["num_heads"], num_classes=c["num_classes"], layernorm_eps=c["layernorm_eps"])


def _model(golden, distilled: bool, antialias: bool = True) -> VisionTransformer:
    cls = DistilledVisionTransformer if distilled else VisionTransformer
    m = cls(_config(golden), pos_embed_antialias=antialias)
    sd = golden["distilled_state_dict" if distilled else "plain_state_dict"]
    # same keys in the same order as upstream's state_dict()
    assert list(m.state_dict()) == list(sd)
    m.load_state_dict(sd, strict=True)
    return m.eval()


def _close(a: torch.Tensor, b: torch.Tensor, name: str) -> None:
    assert a.shape == b.shape, f"{name}: shape {tuple(a.shape)} vs {tuple(b.shape)}"
    err = (a - b).abs().max().item()
    assert err <= TOL, f"{name}: max abs diff {err:.3g} > {TOL}"


@torch.no_grad()
def test_plain(golden):
    m = _model(golden, distilled=False)
    x = golden["x"]
    _close(m.forward_tokens(x), golden["plain_tokens_normed"], "plain_tokens_normed")
    _close(m.forward_features(x), golden["plain_features"], "plain_features")
    _close(m(x), golden["plain_logits_eval"], "plain_logits_eval")


@torch.no_grad()
def test_distilled(golden):
    m = _model(golden, distilled=True)
    x = golden["x"]
    _close(m.forward_tokens(x), golden["distilled_tokens_normed"], "distilled_tokens_normed")
    cls, dist = m.forward_features(x)
    _close(cls, golden["distilled_features_cls"], "distilled_features_cls")
    _close(dist, golden["distilled_features_dist"], "distilled_features_dist")
    _close(m(x), golden["distilled_logits_eval"], "distilled_logits_eval")
    m.train()  # drop rates are 0: train mode changes only the return value (a tuple of both heads)
    a, b = m(x)
    _close(a, golden["distilled_logits_head_cls"], "distilled_logits_head_cls")
    _close(b, golden["distilled_logits_head_dist"], "distilled_logits_head_dist")


@pytest.mark.parametrize("case,distilled,grid", [("a", True, (6, 6)), ("b", False, (3, 5))])
@pytest.mark.parametrize("antialias", [True, False])
@torch.no_grad()
def test_resampled_pos_embed_and_forward(golden, case, distilled, grid, antialias):
    mode = "antialias" if antialias else "noantialias"
    sd = golden["distilled_state_dict" if distilled else "plain_state_dict"]
    ref = golden[f"resample_{case}_pos_embed_{mode}"]
    pe = resample_abs_pos_embed(sd["pos_embed"], grid, num_prefix_tokens=2 if distilled else 1,
                                antialias=antialias)
    _close(pe, ref, f"resample_{case}_pos_embed_{mode}")
    # the two filters really differ on these cases (so the test tells them apart)
    other = golden[f"resample_{case}_pos_embed_{'noantialias' if antialias else 'antialias'}"]
    assert (pe - other).abs().max() > 0.1

    m = _model(golden, distilled, antialias)
    x = golden[f"resample_{case}_x"]
    assert tuple(x.shape[-2:]) == (16 * grid[0], 16 * grid[1])
    _close(m.pos_embed_for(grid), ref, "pos_embed_for")
    _close(m.forward_tokens(x), golden[f"resample_{case}_{mode}_tokens_normed"], f"resample_{case}_{mode}_tokens")
    _close(m(x), golden[f"resample_{case}_{mode}_logits_eval"], f"resample_{case}_{mode}_logits_eval")


def test_resample_identity_and_errors(golden):
    pe = golden["plain_state_dict"]["pos_embed"]
    assert resample_abs_pos_embed(pe, (4, 4), 1) is pe  # timm returns its input for the same square grid
    with pytest.raises(ValueError, match="not a square grid"):
        resample_abs_pos_embed(pe[:, :-1], (3, 3), 1)


@torch.no_grad()
def test_pos_embed_cache_is_reused_and_invalidated(golden):
    m = _model(golden, distilled=False)
    a = m.pos_embed_for((3, 5))
    assert m.pos_embed_for((3, 5)) is a  # cached
    # new weights: the cache must not serve the old resampled embedding
    sd = {k: v.clone() for k, v in golden["plain_state_dict"].items()}
    sd["pos_embed"] = sd["pos_embed"] * 2
    m.load_state_dict(sd)
    b = m.pos_embed_for((3, 5))
    _close(b, 2 * a, "pos_embed after reload")
    # switching the filter clears the cache too
    m.pos_embed_antialias = False
    _close(m.pos_embed_for((3, 5)), resample_abs_pos_embed(sd["pos_embed"], (3, 5), 1, antialias=False), "noaa")


def test_pos_embed_gets_gradients_at_other_sizes(golden):
    m = _model(golden, distilled=True).train()
    x = golden["resample_a_x"]
    with torch.no_grad():
        m.pos_embed_for((6, 6))  # fills the cache: must not cut the graph below
    loss = m.forward_tokens(x)[:, 0].square().sum()
    loss.backward()
    assert m.pos_embed.grad is not None and m.pos_embed.grad[:, 2:].abs().sum() > 0


def test_input_not_multiple_of_patch(golden):
    m = _model(golden, distilled=False)
    with pytest.raises(ValueError, match="multiple of the patch size 16"):
        m.forward_tokens(torch.zeros(1, 3, 64, 70))
