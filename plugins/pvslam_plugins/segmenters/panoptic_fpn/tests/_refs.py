"""Reference implementations shared by the tests (plain Python loops, written from the definitions)."""
from __future__ import annotations

import math

import numpy as np
import torch


def iou_ref(a, b) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def nms_ref(boxes: torch.Tensor, scores: torch.Tensor, thr: float) -> list[int]:
    bl, sl = boxes.tolist(), scores.tolist()
    order = sorted(range(len(sl)), key=lambda i: -sl[i])
    keep: list[int] = []
    for i in order:
        if all(iou_ref(bl[i], bl[j]) <= thr for j in keep):
            keep.append(i)
    return keep


def bilinear_ref(fm: torch.Tensor, y: float, x: float) -> torch.Tensor:
    """torchvision roi_align_kernel bilinear_interpolate, for one point, all channels."""
    c, h, w = fm.shape
    if y < -1.0 or y > h or x < -1.0 or x > w:
        return torch.zeros(c, dtype=torch.float64)
    y, x = max(y, 0.0), max(x, 0.0)
    yl, xl = int(y), int(x)
    if yl >= h - 1:
        yh = yl = h - 1
        y = float(yl)
    else:
        yh = yl + 1
    if xl >= w - 1:
        xh = xl = w - 1
        x = float(xl)
    else:
        xh = xl + 1
    ly, lx = y - yl, x - xl
    hy, hx = 1 - ly, 1 - lx
    f = fm.double()
    return hy * hx * f[:, yl, xl] + hy * lx * f[:, yl, xh] + ly * hx * f[:, yh, xl] + ly * lx * f[:, yh, xh]


def roi_align_ref(feat, rois, out, scale, sampling_ratio, aligned) -> torch.Tensor:
    """torchvision roi_align_forward_kernel, loop by loop; ROI geometry in float32 as the kernel computes it
    (an ROI whose size is an exact multiple of the bin count must get the same sub-grid).  ``out``: an int or
    ``(ph, pw)``."""
    f32 = np.float32
    r = rois.shape[0]
    c = feat.shape[1]
    oh, ow = (out, out) if isinstance(out, int) else out
    res = torch.zeros(r, c, oh, ow, dtype=torch.float64)
    off = f32(0.5 if aligned else 0.0)
    for n in range(r):
        b = int(rois[n, 0])
        x0, y0, x1, y1 = (f32(v) * f32(scale) - off for v in rois[n, 1:].tolist())
        rw, rh = x1 - x0, y1 - y0
        if not aligned:
            rw, rh = max(rw, f32(1.0)), max(rh, f32(1.0))
        bh, bw = rh / f32(oh), rw / f32(ow)
        gh = sampling_ratio if sampling_ratio > 0 else int(math.ceil(rh / f32(oh)))
        gw = sampling_ratio if sampling_ratio > 0 else int(math.ceil(rw / f32(ow)))
        count = max(gh * gw, 1)
        for ph in range(oh):
            for pw in range(ow):
                acc = torch.zeros(c, dtype=torch.float64)
                for iy in range(gh):
                    y = y0 + f32(ph) * bh + f32(iy + 0.5) * bh / f32(gh)
                    for ix in range(gw):
                        x = x0 + f32(pw) * bw + f32(ix + 0.5) * bw / f32(gw)
                        acc += bilinear_ref(feat[b], float(y), float(x))
                res[n, :, ph, pw] = acc / count
    return res
