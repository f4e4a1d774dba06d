"""The initialisation pair's chain check (pvslam_core/slam/bootstrap.py ``chain_checked``): a correspondence of a pair
far apart is kept only where the flows of the keyframes between, chained, stay in view, are confident and land on it."""
import pytest
import torch

from pvslam_core.slam import bootstrap as B

H, W = 6, 8


def _shift(dx: float, dy: float = 0.0) -> torch.Tensor:
    """Positions ``[2, H, W]`` of every pixel moved by ``(dx, dy)``."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    return torch.stack([xs + dx, ys + dy])


def test_a_consistent_chain_keeps_the_pair_and_a_wrong_match_is_dropped():
    links = torch.stack([_shift(1.0), _shift(1.0), _shift(1.0)])  # a -> a+1 -> a+2 -> m, one pixel right each
    direct = _shift(3.0)
    direct[:, 2, 1] += torch.tensor([0.0, 2.5])  # one correspondence that the chain does not reach (2.5 px off)
    weight = torch.full((2, H, W), 0.8)
    out = B.chain_checked(direct, weight, links, torch.ones_like(links), tol=1.0, relative_weight=True)
    kept = out[0] > 0
    # the chain's last link starts from x + 2, which must still be in view (x + 2 <= W - 1); the wrong match is gone
    expect = torch.zeros(H, W, dtype=torch.bool)
    expect[:, : W - 2] = True
    expect[2, 1] = False
    assert torch.equal(kept, expect)
    assert torch.equal(out[:, kept], weight[:, kept])  # kept weights are the pair's own


def test_sub_pixel_links_compose():
    links = torch.stack([_shift(0.5, 0.25), _shift(0.5, 0.25)])
    out = B.chain_checked(_shift(1.0, 0.5), torch.ones(2, H, W), links, torch.ones_like(links), tol=0.01,
                          relative_weight=True)
    kept = out[0] > 0
    # exactly what the first link keeps in view (x + 0.5 <= W - 1 and y + 0.25 <= H - 1) lands within 0.01 px
    expect = torch.zeros(H, W, dtype=torch.bool)
    expect[: H - 1, : W - 1] = True
    assert torch.equal(kept, expect)
    # the same pair against a chain that went elsewhere: nothing kept
    other = torch.stack([_shift(-1.0), _shift(-1.0)])
    moved = B.chain_checked(_shift(1.0, 0.5), torch.ones(2, H, W), other, torch.ones_like(other), tol=1.0,
                            relative_weight=True)
    assert not bool((moved > 0).any())


def test_a_pixel_that_passes_an_unconfident_link_pixel_is_dropped():
    links = torch.stack([_shift(1.0), _shift(0.0, 1.0)])  # right, then down
    lw = torch.ones_like(links)
    lw[1, :, 3, 4] = 0.0  # the second link is not confident at (x 4, y 3) of view a+1
    out = B.chain_checked(_shift(1.0, 1.0), torch.ones(2, H, W), links, lw, tol=0.5, relative_weight=True)
    kept = out[0] > 0
    assert not kept[3, 3]  # (3, 3) -> (4, 3): through the unconfident pixel
    # every other pixel whose first link stays in view (the last column leaves it)
    assert int(kept[: H - 1, : W - 1].sum()) == (H - 1) * (W - 1) - 1 and not bool(kept[:, W - 1].any())


def test_chain_follow_lands_each_pixel_and_keeps_its_least_confidence():
    """``chain_follow``: where each view-a pixel lands after the links (the sum of the shifts), whether every link
    kept it in view and confident, and the least confidence met on the way (0 where it was lost)."""
    links = torch.stack([_shift(1.0), _shift(0.5, 1.0)])
    lw = torch.ones_like(links)
    lw[0] *= 0.9
    lw[1, :, 2, 3] = 0.6  # the second link is less confident at (x 3, y 2) of view a+1
    pos, ok, conf = B.chain_follow(links, lw, relative_weight=True)
    expect = torch.zeros(H, W, dtype=torch.bool)
    expect[:, : W - 1] = True  # every link starts in view (the second from x + 1) ...
    assert torch.equal(ok, expect)
    pos, ok, conf = B.chain_follow(links, lw, relative_weight=True, land_in_view=True)
    expect[H - 1] = False  # ... and lands in view only above the last row (y + 1) and left of the last column
    expect[:, W - 2] = False  # (x + 1.5)
    assert torch.equal(ok, expect)
    assert torch.allclose(pos[:, ok], _shift(1.5, 1.0)[:, ok])
    assert float(conf[2, 2]) == pytest.approx(0.6) and float(conf[ok].max()) == pytest.approx(0.9)
    assert not bool(conf[~ok].any())
