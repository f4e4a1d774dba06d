"""bench/realism.py: the image statistics it compares real and generated frames by, on images whose answer is known."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import realism  # noqa: E402


def _smooth(h: int = 240, w: int = 320) -> np.ndarray:
    ys, xs = np.mgrid[0:h, 0:w]
    return 100 + 40 * np.sin(xs / 37.0) + 30 * np.cos(ys / 23.0)  # float, no detail at the pixel scale


@pytest.mark.parametrize("sigma", [1.0, 2.0, 4.0])
def test_the_noise_estimate_finds_added_noise_and_ignores_smooth_content(sigma):
    rng = np.random.default_rng(0)
    clean = np.clip(np.round(_smooth()), 0, 255).astype(np.uint8)
    noisy = np.clip(np.round(_smooth() + rng.normal(0, sigma, clean.shape)), 0, 255).astype(np.uint8)
    assert realism.noise_sigma(clean) < 0.5  # rounding only
    assert realism.noise_sigma(noisy) == pytest.approx(sigma, rel=0.15)


def test_sharpness_clipping_and_the_exposure_step():
    import cv2

    rng = np.random.default_rng(1)
    detail = rng.integers(0, 256, (240, 320)).astype(np.uint8)  # detail down to the pixel
    soft = cv2.GaussianBlur(detail, (0, 0), 2.0)
    tau = 1e-3
    assert realism.frame_stats(detail, tau)["sharpness"] < 0.5 < realism.frame_stats(soft, tau)["sharpness"]
    half = np.full((240, 320), 128, np.uint8)
    half[:60] = 255
    half[60:90] = 0
    assert realism.frame_stats(half, tau)["clipped"] == pytest.approx(90 / 240)
    assert realism.frame_stats(half, tau)["weak_texture"] > 0.9  # flat everywhere but two edges
    # brightness x1.5 every other frame: |log 1.5| between every pair of neighbours
    frames = [np.full((40, 40), 100 if k % 2 == 0 else 150, np.uint8) for k in range(6)]
    assert realism.sequence_stats(frames, tau)["exposure_step"] == pytest.approx(np.log(1.5), rel=1e-6)
    with pytest.raises(ValueError):
        realism.sequence_stats(frames[:1], tau)
