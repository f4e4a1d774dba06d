"""Synthetic test scenes for the flow frontend: textured photos (scikit-image) under known warps."""
from __future__ import annotations

import cv2
import numpy as np
import skimage.data as skd
import torch

from pvslam_core.types import Frame, Intrinsics, PanopticSegmentation, Segment

H, W = 240, 320
PAD = 60
INTR = Intrinsics(fx=288.0, fy=288.0, cx=(W - 1) / 2, cy=(H - 1) / 2, width=W, height=H)


def texture(name: str = "astronaut", size=(H + 2 * PAD, W + 2 * PAD)) -> np.ndarray:
    img = getattr(skd, name)()
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    return cv2.resize(img[..., :3], (size[1], size[0]), interpolation=cv2.INTER_AREA)


def affine_view(big: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """View of ``big`` (cropped to HxW at PAD) after the affine map ``q = c + L (p - c) + t`` (c = image centre).

    Returns the warped HxW RGB image and the exact flow ``[H, W, 2]`` from the unwarped crop to it.
    """
    L, t = A[:, :2].astype(np.float64), A[:, 2].astype(np.float64)
    c_big = np.array([PAD + (W - 1) / 2, PAD + (H - 1) / 2])
    M = np.hstack([L, (c_big - L @ c_big + t)[:, None]]).astype(np.float32)
    warped = cv2.warpAffine(big, M, (big.shape[1], big.shape[0]), flags=cv2.INTER_LINEAR)
    img = np.ascontiguousarray(warped[PAD:PAD + H, PAD:PAD + W])
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    P = np.stack([xs, ys], -1)
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    Q = (P - c) @ L.T + c + t
    return img, (Q - P).astype(np.float32)


def shifted(big: np.ndarray, dx: float, dy: float = 0.0) -> np.ndarray:
    return affine_view(big, np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]]))[0]


def base(big: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(big[PAD:PAD + H, PAD:PAD + W])


def frame(img: np.ndarray, index: int = 0) -> Frame:
    return Frame(index=index, timestamp=index * 0.1, image=torch.from_numpy(img).permute(2, 0, 1).contiguous(),
                 intrinsics=INTR)


def with_patch(img: np.ndarray, patch: np.ndarray, x0: int, y0: int) -> np.ndarray:
    out = img.copy()
    ph, pw = patch.shape[:2]
    out[y0:y0 + ph, x0:x0 + pw] = patch
    return out


def patch_segmentation(x0: int, y0: int, ph: int, pw: int, car_id: int = 26001, bg_id: int = 11000):
    """Panoptic ids: a 'car' thing segment at the patch, 'building' stuff elsewhere."""
    ids = torch.full((H, W), bg_id, dtype=torch.int64)
    ids[y0:y0 + ph, x0:x0 + pw] = car_id
    segs = [Segment(id=bg_id, category_id=11, isthing=False), Segment(id=car_id, category_id=26, isthing=True)]
    return PanopticSegmentation(ids=ids, segments=segs)


def identity_reproject(h: int, w: int, valid=None):
    """``(reproject_fn, coords)`` for ``FlowFrontend(reproject_fn=...)`` or :func:`masking`: the estimate maps each of
    the ``h x w`` BA pixels onto itself (``coords`` float64 ``[h, w, 2]``, (x, y)), and every pixel can be judged
    unless ``valid`` (bool ``[h, w]``) says otherwise.  An edge's residual is then its target's own shift
    (:func:`shifted_target`)."""
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    coords = torch.stack([xs, ys], -1)
    ok = torch.ones(h, w, dtype=torch.bool) if valid is None else valid

    def reproject(poses, disps, intr, ii, jj):
        return coords[None].expand(len(ii), -1, -1, -1), ok[None].expand(len(ii), -1, -1)

    return reproject, coords


def shifted_target(coords: torch.Tensor, du: torch.Tensor) -> torch.Tensor:
    """An edge's target ``[2, h, w]``: each pixel of ``coords`` ``[h, w, 2]`` moved by ``du`` ``[h, w]`` BA px along u."""
    return (coords + torch.stack([du, torch.zeros_like(du)], -1)).permute(2, 0, 1)


def masking(h: int, w: int, keyframes: dict, reproject, **cfg):
    """A :class:`~pvslam_plugins.frontends.flow.dynamic_masking.DynamicMasking` (``frontend.dynamic`` settings ``cfg``)
    with keyframes ``{id: (ids int64 [h, w] or None, movable thing ids)}`` given at the BA resolution ``h x w``."""
    from pvslam_core.slam.dynamic_config import DynamicMaskingConfig
    from pvslam_plugins.frontends.flow.dynamic_masking import DynamicMasking

    m = DynamicMasking(DynamicMaskingConfig(**cfg), reproject)
    for sid, (ids, things) in keyframes.items():
        seg = None
        if ids is not None:
            segs = [Segment(id=i, category_id=1, isthing=i in things) for i in ids.unique().tolist() if i != 0]
            seg = PanopticSegmentation(ids=ids, segments=segs)
        m.add_keyframe(sid, seg, h, w)
    return m


class TwoKeyframeGraph:
    """The attributes the frontend's dynamic masking reads: two keyframes of ``h x w`` BA pixels with different
    poses (the second 1 m along z), unit inverse depth, intrinsics ``(10, 10, w / 2, h / 2)``."""

    def __init__(self, h: int, w: int):
        self.ba_shape = (h, w)
        self.poses = torch.tensor([[0, 0, 0, 0, 0, 0, 1.0], [0, 0, 1.0, 0, 0, 0, 1.0]], dtype=torch.float64)
        self.disps = torch.ones(2, h, w, dtype=torch.float64)
        self.intrinsics = torch.tensor([10.0, 10.0, w / 2, h / 2], dtype=torch.float64)
        self.ids = torch.tensor([0, 1])
