"""The depth-consistency cue (dynamic.depth_candidates): a vehicle driving along the camera's direction of travel
(its flow is epipolar-consistent, the residual test cannot see it) whose depth estimates disagree across two
keyframes is flagged, static structure is not; checked against a per-pixel brute-force reference."""
import math

import torch

from pvslam_plugins.frontends.flow import dynamic as D

H, W = 12, 16
FX = FY = 10.0
CX, CY = W / 2 - 0.5, H / 2 - 0.5


def _bilinear(img, u, v):
    """Brute-force bilinear sample of ``img [H, W]`` at (u, v) (inside the image)."""
    x0, y0 = int(math.floor(u)), int(math.floor(v))
    x1, y1 = min(x0 + 1, W - 1), min(y0 + 1, H - 1)
    a, b = u - x0, v - y0
    return ((1 - a) * (1 - b) * img[y0, x0] + a * (1 - b) * img[y0, x1] + (1 - a) * b * img[y1, x0]
            + a * b * img[y1, x1])


def _scene():
    """Keyframe j is 1 m ahead of keyframe i (pure forward motion).  Static wall at 10 m; a car at 5 m in i's
    centre that drove away between the keyframes: j's own estimate puts it at 8 m (a static point would be at 4 m)."""
    disp_i = torch.full((H, W), 0.1, dtype=torch.float64)
    car = torch.zeros(H, W, dtype=torch.bool)
    car[4:8, 5:11] = True
    disp_i[car] = 0.2
    R = torch.eye(3, dtype=torch.float64)[None]
    t = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)  # camera i -> camera j
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    x0, y0 = (xs - CX) / FX, (ys - CY) / FY
    Z = 1.0 + t[0, 2] * disp_i
    coords = torch.stack([FX * x0 / Z + CX, FY * y0 / Z + CY], -1)[None]  # [1, H, W, 2]
    valid = ((coords[0, ..., 0] >= 0) & (coords[0, ..., 0] <= W - 1) & (coords[0, ..., 1] >= 0)
             & (coords[0, ..., 1] <= H - 1))[None]
    # j's estimate: the wall at 9 m, the car (its footprint in j) at 8 m
    disp_j = torch.full((H, W), 1 / 9, dtype=torch.float64)
    cu, cv = coords[0, ..., 0][car], coords[0, ..., 1][car]
    disp_j[int(cv.min().floor()):int(cv.max().ceil()) + 1, int(cu.min().floor()):int(cu.max().ceil()) + 1] = 1 / 8
    return R, t, disp_i[None], disp_j[None], coords, valid, car


def test_depth_candidates_flag_the_car_not_the_wall():
    R, t, di, dj, coords, valid, car = _scene()
    intr = torch.tensor([FX, FY, CX, CY])
    out = D.depth_candidates(R, t, di, dj, coords, valid, intr, thresh=0.5)[0]
    # brute force: predicted inverse depth in j = d / (1 - d) (1 m forward), j's estimate sampled bilinearly
    seen, judged = {}, []
    for y in range(H):
        for x in range(W):
            if valid[0, y, x]:
                d = float(di[0, y, x])
                seen[(y, x)] = (d / (1 - d), float(_bilinear(dj[0], float(coords[0, y, x, 0]),
                                                            float(coords[0, y, x, 1]))))
    med = sorted(s for _, s in seen.values())[(len(seen) - 1) // 2]
    for y in range(H):
        for x in range(W):
            exp = (y, x) in seen and abs(seen[(y, x)][0] - seen[(y, x)][1]) > 0.5 * med
            assert bool(out[y, x]) == exp, (y, x)
    assert bool(out[car & valid[0]].all())  # predicted 1/4, seen 1/8: the car moved
    assert int(out[~car].sum()) == 0  # the wall agrees (1/9 both ways), even next to the car
    # a static car (j's estimate is where a static point would be) is consistent: nothing flagged
    cu, cv = coords[0, ..., 0][car], coords[0, ..., 1][car]
    dj2 = dj.clone()
    dj2[0, int(cv.min().floor()):int(cv.max().ceil()) + 1, int(cu.min().floor()):int(cu.max().ceil()) + 1] = 0.25
    assert int(D.depth_candidates(R, t, di, dj2, coords, valid, intr, thresh=0.5)[0][car].sum()) == 0


def test_depth_candidates_judge_only_valid_pixels_and_handle_no_edges():
    R, t, di, dj, coords, valid, car = _scene()
    intr = torch.tensor([FX, FY, CX, CY])
    none = torch.zeros_like(valid)
    assert int(D.depth_candidates(R, t, di, dj, coords, none, intr, 0.5).sum()) == 0
    e = D.depth_candidates(R[:0], t[:0], di[:0], dj[:0], coords[:0], valid[:0], intr, 0.5)
    assert tuple(e.shape) == (0, H, W)
