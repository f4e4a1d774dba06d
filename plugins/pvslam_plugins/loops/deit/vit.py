"""timm-0.3.3 ``VisionTransformer`` and DeiT ``DistilledVisionTransformer`` in plain torch (paper eq. 9-11, 13).

Parameter names and shapes are those of the upstream modules, so the official DeiT ``.pth`` files load strictly:
``cls_token [1,1,D]``, ``pos_embed [1,P+G,D]`` (P = 1 prefix token, 2 for distilled; G = grid cells),
``[dist_token [1,1,D]]``, ``patch_embed.proj [D,3,p,p]``, ``blocks.i.{norm1, attn.qkv [3D,D], attn.proj, norm2,
mlp.fc1 [rD,D], mlp.fc2}``, ``norm``, ``head [C,D]``, ``[head_dist]``.

Numerics that must match upstream (checked against ``deit_vit_golden.pt`` to <= 1e-5):

* token sequence ``[cls, (dist), patches row-major (y, then x)]``, position embedding added after the concat;
* pre-norm blocks ``x + attn(norm1(x))``, ``x + mlp(norm2(x))``; every LayerNorm has eps 1e-6 (deit/models.py passes
  it; timm's own default would be 1e-5); the MLP uses the exact erf GELU (``nn.GELU()``), not the tanh form;
* attention: the 3D rows of ``qkv`` are ``[q | k | v]``, each split into heads; scale ``head_dim ** -0.5``.

Unlike v0.3.3 (which asserts the input equals ``img_size``), any input whose sides are multiples of the patch size
works: the stored ``pos_embed`` grid is resampled with :func:`resample_abs_pos_embed` (timm's function, see there
for the two modes) and the result is cached per grid size.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Optional, Union

import torch
import torch.nn.functional as F
from torch import nn

Size2 = tuple[int, int]


# --------------------------------------------------------------------------------------------------------------
# position-embedding resampling
# --------------------------------------------------------------------------------------------------------------
def resample_abs_pos_embed(
    pos_embed: torch.Tensor,
    new_size: Size2,
    num_prefix_tokens: int = 1,
    old_size: Optional[Size2] = None,
    interpolation: str = "bicubic",
    antialias: bool = True,
) -> torch.Tensor:
    """timm's ``resample_abs_pos_embed`` (timm/layers/pos_embed.py): ``[1, P+gh*gw, D]`` -> ``[1, P+H'*W', D]``.

    The ``num_prefix_tokens`` rows (cls, and dist for DeiT-distilled) are kept unchanged; the grid rows, assumed
    square unless ``old_size`` is given, are interpolated as an NCHW float32 image with ``align_corners=False``
    and cast back.  The input is returned untouched when the token count already matches and the grid is square.

    ``antialias`` selects the filter of ``F.interpolate(mode='bicubic')``, and it matters even when upsampling:

    * ``True`` (timm's default, also what timm's ``checkpoint_filter_fn`` and ``dynamic_img_size`` use): the
      PIL-style separable filter, cubic coefficient a = -0.5, support 2*max(scale, 1), border weights truncated
      and renormalised;
    * ``False``: classic bicubic convolution, a = -0.75 with border index clamping.  This is what the official
      DeiT fine-tuning at other resolutions used (deit/main.py ``--finetune``: bicubic, align_corners=False, no
      antialias), and timm's deprecated ``resize_pos_embed``.

    Both were checked to reproduce the golden fixture bitwise (torch's kernels are what timm calls), so no
    hand-written filter is needed.
    """
    if pos_embed.dim() != 3 or pos_embed.shape[0] != 1:
        raise ValueError(f"pos_embed must be [1, N, D], got {tuple(pos_embed.shape)}")
    gh, gw = int(new_size[0]), int(new_size[1])
    n_old = pos_embed.shape[1] - num_prefix_tokens
    if old_size is None:
        side = math.isqrt(n_old)
        if side * side != n_old:
            raise ValueError(f"pos_embed has {n_old} grid tokens (after {num_prefix_tokens} prefix tokens), not a "
                             "square grid: pass old_size")
        old_size = (side, side)
    oh, ow = int(old_size[0]), int(old_size[1])
    if oh * ow != n_old:
        raise ValueError(f"old_size {old_size} does not hold the {n_old} grid tokens of pos_embed")
    if gh * gw == n_old and gh == gw:  # timm's early return (also when old_size is non-square with equal count)
        return pos_embed
    dim = pos_embed.shape[-1]
    prefix, grid = pos_embed[:, :num_prefix_tokens], pos_embed[:, num_prefix_tokens:]
    grid = grid.reshape(1, oh, ow, dim).permute(0, 3, 1, 2).float()  # [1, D, oh, ow]
    grid = F.interpolate(grid, size=(gh, gw), mode=interpolation, antialias=antialias, align_corners=False)
    grid = grid.permute(0, 2, 3, 1).reshape(1, gh * gw, dim).to(pos_embed.dtype)
    return torch.cat([prefix, grid], dim=1)


# --------------------------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------------------------
@dataclass
class ViTConfig:
    """Architecture of a (DeiT) ViT.  ``img_size`` fixes the stored pos_embed grid (img_size / patch_size)."""

    img_size: Size2 = (224, 224)
    patch_size: int = 16
    embed_dim: int = 768
    depth: int = 12
    num_heads: int = 12
    mlp_ratio: float = 4.0
    qkv_bias: bool = True
    num_classes: int = 1000  # 0: no head (and no head_dist), as timm
    distilled: bool = False
    layernorm_eps: float = 1e-6
    drop_path_rate: float = 0.0  # stochastic depth (training only; DeiT-base trained with 0.1)
    pos_embed_antialias: bool = True  # see resample_abs_pos_embed

    def __post_init__(self) -> None:
        if isinstance(self.img_size, int):
            self.img_size = (self.img_size, self.img_size)
        self.img_size = (int(self.img_size[0]), int(self.img_size[1]))
        if self.embed_dim % self.num_heads:
            raise ValueError(f"embed_dim {self.embed_dim} is not divisible by num_heads {self.num_heads}")
        if self.img_size[0] % self.patch_size or self.img_size[1] % self.patch_size:
            raise ValueError(f"img_size {self.img_size} is not a multiple of patch_size {self.patch_size}")

    @property
    def grid_size(self) -> Size2:
        return (self.img_size[0] // self.patch_size, self.img_size[1] // self.patch_size)

    @property
    def num_prefix_tokens(self) -> int:
        return 2 if self.distilled else 1

    @property
    def variant(self) -> str:
        return "distilled" if self.distilled else "plain"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["img_size"] = list(self.img_size)
        return d


#: full-size presets (deit/models.py); the official checkpoints have 152 (plain) / 155 (distilled) keys
PRESETS: dict[str, ViTConfig] = {
    "deit_base_patch16_224": ViTConfig(),
    "deit_base_distilled_patch16_224": ViTConfig(distilled=True),
}


# --------------------------------------------------------------------------------------------------------------
# modules (names as timm v0.3.3)
# --------------------------------------------------------------------------------------------------------------
class PatchEmbed(nn.Module):
    def __init__(self, patch_size: int, embed_dim: int, in_chans: int = 3) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, 3, H, W] -> [B, gh*gw, D] row-major
        return self.proj(x).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    def __init__(self, dim: int, num_heads: int, qkv_bias: bool) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.scale = (dim // num_heads) ** -0.5
        self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [B, N, D]
        B, N, D = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, D // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # [B, heads, N, head_dim] each
        # fused kernel: same softmax(q k^T * scale) v as upstream (differs by float rounding only, ~1e-7 here)
        out = F.scaled_dot_product_attention(q, k, v, scale=self.scale)
        return self.proj(out.transpose(1, 2).reshape(B, N, D))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()  # exact erf form, as upstream
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class DropPath(nn.Module):
    """Stochastic depth per sample (identity in eval mode or with p = 0); has no parameters."""

    def __init__(self, p: float) -> None:
        super().__init__()
        self.p = float(p)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or self.p == 0.0:
            return x
        keep = 1.0 - self.p
        mask = x.new_empty((x.shape[0],) + (1,) * (x.dim() - 1)).bernoulli_(keep)
        return x * mask / keep


class Block(nn.Module):
    """Pre-norm transformer block: eq. 10 (``x + MSA(LN(x))``) and eq. 11 (``x + MLP(LN(x))``)."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, qkv_bias: bool, eps: float,
                 drop_path: float = 0.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=eps)
        self.attn = Attention(dim, num_heads, qkv_bias)
        self.drop_path = DropPath(drop_path)
        self.norm2 = nn.LayerNorm(dim, eps=eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.drop_path(self.attn(self.norm1(x)))
        return x + self.drop_path(self.mlp(self.norm2(x)))


class VisionTransformer(nn.Module):
    """timm v0.3.3 ``VisionTransformer`` (plain DeiT) with input-size-agnostic position embeddings.

    ``forward_tokens(x [B,3,H,W]) -> [B, P+gh*gw, D]`` is the output of the final ``norm`` over all tokens (the
    descriptor is read from it); ``forward_features`` and ``forward`` return what upstream returns.
    """

    def __init__(self, config: Optional[ViTConfig] = None, **overrides) -> None:
        super().__init__()
        # always a private copy: the presets (and the caller's object) must not change with this model
        cfg = ViTConfig(**{**(config or ViTConfig()).to_dict(), **overrides})
        if cfg.distilled and not isinstance(self, DistilledVisionTransformer):
            raise ValueError("a distilled config needs DistilledVisionTransformer (or build_vit)")
        self.config = cfg
        D = cfg.embed_dim
        self.num_prefix_tokens = cfg.num_prefix_tokens
        self.patch_embed = PatchEmbed(cfg.patch_size, D)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, D))
        self.pos_embed = nn.Parameter(torch.zeros(1, cfg.num_prefix_tokens + cfg.grid_size[0] * cfg.grid_size[1], D))
        dpr = [cfg.drop_path_rate * i / max(cfg.depth - 1, 1) for i in range(cfg.depth)]  # linearly increasing
        self.blocks = nn.ModuleList(
            Block(D, cfg.num_heads, cfg.mlp_ratio, cfg.qkv_bias, cfg.layernorm_eps, dpr[i]) for i in range(cfg.depth)
        )
        self.norm = nn.LayerNorm(D, eps=cfg.layernorm_eps)
        self.head = nn.Linear(D, cfg.num_classes) if cfg.num_classes > 0 else nn.Identity()
        # (grid h, grid w) -> (validity key, resampled pos_embed); not part of the state_dict
        self._pos_cache: dict[Size2, tuple[tuple, torch.Tensor]] = {}
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """timm's init (truncated normal std .02 for tokens and linear weights, zero biases, unit LayerNorms)."""
        for name, p in self.named_parameters():
            if name.endswith("token") or name == "pos_embed":
                nn.init.trunc_normal_(p, std=0.02)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.LayerNorm):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    # --- position embedding --------------------------------------------------------------------------------
    @property
    def pos_embed_antialias(self) -> bool:
        return self.config.pos_embed_antialias

    @pos_embed_antialias.setter
    def pos_embed_antialias(self, value: bool) -> None:
        self.config.pos_embed_antialias = bool(value)
        self._pos_cache.clear()

    def pos_embed_for(self, grid: Size2) -> torch.Tensor:
        """``[1, P + gh*gw, D]`` position embedding for a patch grid (resampled from the stored grid, cached).

        The cache is used only when no gradient flows into ``pos_embed`` (a cached tensor would cut the graph),
        and an entry is valid only for the parameter's current storage and in-place version (``load_state_dict``,
        optimiser steps and ``.to()`` all change one of them), so it never serves stale values.
        """
        grid = (int(grid[0]), int(grid[1]))
        pe = self.pos_embed
        if grid == self.config.grid_size:
            return pe
        caching = not (torch.is_grad_enabled() and pe.requires_grad)
        key = (pe._version, pe.data_ptr(), pe.dtype, pe.device, self.config.pos_embed_antialias)
        if caching:
            hit = self._pos_cache.get(grid)
            if hit is not None and hit[0] == key:
                return hit[1]
        out = resample_abs_pos_embed(pe, grid, self.num_prefix_tokens, old_size=self.config.grid_size,
                                     antialias=self.config.pos_embed_antialias)
        if caching:
            out = out.detach()
            self._pos_cache[grid] = (key, out)
        return out

    # --- forward -------------------------------------------------------------------------------------------
    def _prefix_tokens(self, B: int) -> list[torch.Tensor]:
        return [self.cls_token.expand(B, -1, -1)]

    def forward_tokens(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` normalised images ``[B, 3, H, W]`` (H, W multiples of the patch size) -> ``[B, P+gh*gw, D]``."""
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"expected images [B, 3, H, W], got {tuple(x.shape)}")
        p = self.config.patch_size
        H, W = x.shape[-2:]
        if H % p or W % p:
            raise ValueError(f"input {H}x{W} is not a multiple of the patch size {p}")
        B = x.shape[0]
        tokens = self.patch_embed(x)  # [B, gh*gw, D]
        t = torch.cat(self._prefix_tokens(B) + [tokens], dim=1) + self.pos_embed_for((H // p, W // p))  # eq. 9
        for blk in self.blocks:
            t = blk(t)
        return self.norm(t)

    def forward_features(self, x: torch.Tensor) -> torch.Tensor:
        """The layer-normed class token ``[B, D]`` (upstream ``forward_features``; eq. 12 before the PCA)."""
        return self.forward_tokens(x)[:, 0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.forward_features(x))


class DistilledVisionTransformer(VisionTransformer):
    """DeiT ``DistilledVisionTransformer`` (deit/models.py): adds ``dist_token`` and ``head_dist``.

    ``forward_features`` returns ``(cls, dist)``; ``forward`` returns ``(head(cls), head_dist(dist))`` in training
    mode and their mean in eval mode, as upstream.
    """

    def __init__(self, config: Optional[ViTConfig] = None, **overrides) -> None:
        cfg = config or ViTConfig(distilled=True)
        if not cfg.distilled:
            cfg = ViTConfig(**{**cfg.to_dict(), "distilled": True})
        super().__init__(cfg, **overrides)
        D = self.config.embed_dim
        self.dist_token = nn.Parameter(torch.zeros(1, 1, D))
        nn.init.trunc_normal_(self.dist_token, std=0.02)
        self.head_dist = nn.Linear(D, self.config.num_classes) if self.config.num_classes > 0 else nn.Identity()
        if isinstance(self.head_dist, nn.Linear):
            nn.init.trunc_normal_(self.head_dist.weight, std=0.02)
            nn.init.zeros_(self.head_dist.bias)

    def _prefix_tokens(self, B: int) -> list[torch.Tensor]:
        return [self.cls_token.expand(B, -1, -1), self.dist_token.expand(B, -1, -1)]

    def forward_features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # type: ignore[override]
        t = self.forward_tokens(x)
        return t[:, 0], t[:, 1]

    def forward(self, x: torch.Tensor) -> Union[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        cls, dist = self.forward_features(x)
        a, b = self.head(cls), self.head_dist(dist)
        return (a, b) if self.training else (a + b) / 2


def build_vit(config: ViTConfig, empty: bool = False) -> VisionTransformer:
    """The right class for ``config.distilled``.  ``empty``: parameters allocated but not initialised (built on
    the meta device, then materialised): for models whose weights are loaded right after (86 M random draws cost
    seconds)."""
    cls = DistilledVisionTransformer if config.distilled else VisionTransformer
    if not empty:
        return cls(config)
    with torch.device("meta"):
        model = cls(config)
    return model.to_empty(device="cpu")


def _preset(name: str, **overrides) -> VisionTransformer:
    cfg = PRESETS[name]
    return build_vit(ViTConfig(**{**cfg.to_dict(), **overrides}))


def deit_base_patch16_224(**overrides) -> VisionTransformer:
    """DeiT-base (86.6 M parameters, 152 state_dict keys); ``overrides`` change ViTConfig fields."""
    return _preset("deit_base_patch16_224", **overrides)


def deit_base_distilled_patch16_224(**overrides) -> DistilledVisionTransformer:
    """DeiT-base-distilled (87.3 M parameters, 155 state_dict keys)."""
    return _preset("deit_base_distilled_patch16_224", **overrides)  # type: ignore[return-value]
