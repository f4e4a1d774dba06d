"""Helpers of the detectron2 golden test: weights as a model-zoo pickle, one recorded run per image, comparisons.

``shared/fixtures/panoptic_fpn_golden.pt`` (README section D) holds detectron2's PanopticFPN outputs; the tolerances
below are the README's.  A run records what the model computes on the stored network input (end to end, through
``PanopticFPN.decode``) and, stage by stage, what each stage computes from the *stored* inputs of that stage.
"""
from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any, Callable

import torch

from pvslam_plugins.segmenters.panoptic_fpn.model import ROI_LEVELS, PanopticFPN
from pvslam_plugins.segmenters.panoptic_fpn.panoptic import combine, detector_postprocess, semantic_postprocess
from pvslam_plugins.segmenters.panoptic_fpn.roi_heads import Detections, paste_masks

ATOL_DENSE = 1e-4  # backbone, FPN, RPN and semantic tensors
ATOL_ROI = 5e-4  # ROI-pooled features and head outputs
RTOL = 1e-4
BOX_PX = 1e-2  # proposals and detections match as sets: boxes within this many pixels
RANK_SWAP = 1e-5  # two entries may swap ranks (or trade places at a cut-off) when their scores differ by less
PIXEL_AGREEMENT = 0.999
#: the README's cfg changes (score threshold, combine thresholds), set through the segmenter's own options
CFG_CHANGES = {"score_thresh": 0.25, "instances_confidence_thresh": 0.27, "stuff_area_limit": 1024}


def golden_state_dict(golden: dict) -> dict[str, torch.Tensor]:
    """README D: int8 codes times their power-of-two scale, the other tensors as stored; upstream key order."""
    q, scale, fp32 = golden["state_dict_int8"], golden["state_dict_int8_scale"], golden["state_dict_fp32"]
    return {k: q[k].float() * scale[k] if k in q else fp32[k] for k in golden["meta"]["state_dict_keys"]}


def write_model_zoo_pkl(sd: dict[str, torch.Tensor], path: Path) -> Path:
    """The layout of detectron2's ``model_final_*.pkl``: ``{"model": {name: ndarray}, "__author__": ...}``."""
    model = {k: v.numpy() for k, v in sd.items()}
    with open(path, "wb") as f:
        pickle.dump({"model": model, "__author__": "Detectron2 Model Zoo"}, f, protocol=4)
    return path


def crop(t: torch.Tensor, stride: int) -> torch.Tensor:
    """The README's bottom-right window: the last 64 input pixels at this stride (at least one cell)."""
    c = max(64 // stride, 1)
    return t[..., -c:, -c:]


def decode_rle(g: dict) -> torch.Tensor:
    """Pasted masks ``[N, H, W]`` from the stored row-major run lengths (0-run first, runs alternate)."""
    h, w = int(g["height"]), int(g["width"])
    runs, lens = g["inst_masks_rle_counts"].long(), g["inst_masks_rle_len"].long()
    ends = torch.cumsum(runs, 0)  # every mask's runs cover h * w pixels, so masks follow each other
    rank = torch.arange(int(lens.sum())) - torch.repeat_interleave(torch.cumsum(lens, 0) - lens, lens)
    ones = rank % 2 == 1  # a mask's runs 1, 3, 5, ... are its pixels
    edges = torch.zeros(len(lens) * h * w + 1, dtype=torch.int32)
    n = int(ones.sum())
    edges.index_add_(0, (ends - runs)[ones], torch.ones(n, dtype=torch.int32))
    edges.index_add_(0, ends[ones], torch.full((n,), -1, dtype=torch.int32))
    return torch.cumsum(edges[:-1], 0).view(len(lens), h, w) > 0


class Recorder:
    """Forward hooks that keep (a slice of) chosen modules' outputs, under the phase being run."""

    def __init__(self, model: PanopticFPN) -> None:
        self.phase = ""
        self.out: dict[str, dict[str, Any]] = {}
        rh = model.roi_heads
        keep: dict[torch.nn.Module, tuple[str, Callable[[Any], Any]]] = {
            model.backbone.bottom_up: ("res", lambda o: o),
            model.proposal_generator.rpn_head: ("rpn_head", lambda o: o),
            model.proposal_generator: ("proposals", lambda o: o[0]),
            model.sem_seg_head.predictor: ("sem_stride4", lambda o: o[0]),
            model.sem_seg_head: ("sem_padded", lambda o: o[0]),
            rh.box_pooler: ("box_pooled_first4", lambda o: o[:4].clone()),
            rh.box_head: ("box_features_first16", lambda o: o[:16].clone()),
            rh.mask_pooler: ("mask_pooled_first2", lambda o: o[:2].clone()),
        }
        self.handles = [m.register_forward_hook(self._hook(name, f)) for m, (name, f) in keep.items()]

    def _hook(self, name: str, take: Callable[[Any], Any]):
        def hook(module, args, output):
            self.out.setdefault(self.phase, {})[name] = take(output)
        return hook

    def remove(self) -> None:
        for h in self.handles:
            h.remove()


def model_input(g: dict) -> torch.Tensor:
    """The stored network input (resized, before normalisation) as the RGB uint8 frame pvslam passes."""
    if "model_input_gray_uint8" in g:
        return g["model_input_gray_uint8"][None].repeat(3, 1, 1)
    return g["model_input_uint8"].flip(0)  # stored BGR


@torch.no_grad()
def run_image(model: PanopticFPN, g: dict) -> dict[str, Any]:
    """End to end from the stored model input, then every later stage from its stored inputs."""
    rec = Recorder(model)
    try:
        rec.phase = "e2e"
        batch, sizes, _ = model.preprocess([model_input(g)])
        frame = (int(g["height"]), int(g["width"]))
        pyramid = model.extract_normalised(batch, sizes, [frame])
        out = model.decode(pyramid)[0]
        run: dict[str, Any] = {"batch": batch, "sizes": sizes, "pyramid": pyramid, "out": out}
        run.update(rec.out["e2e"])
        run["sem_out"] = semantic_postprocess(run["sem_padded"], sizes[0], frame)
        rec.phase = "stage"
        run["stage"] = _stages(model, g, pyramid.select(ROI_LEVELS), sizes[0], frame)
        run["stage"].update(rec.out["stage"])
    finally:
        rec.remove()
    return run


def _stages(model: PanopticFPN, g: dict, feats: list[torch.Tensor], size: tuple[int, int],
            frame: tuple[int, int]) -> dict[str, Any]:
    """Box head on the stored proposals, detections from the stored box outputs, masks of the stored detections,
    pasting of the stored mask probabilities (into the stored final boxes, and through the rescaling of the stored
    detections), panoptic combine of the stored instances and semantic labels."""
    rh, box = model.roi_heads, g["box"]
    props = g["rpn"]["proposal_boxes"]
    cls_logits, deltas = rh.box_outputs(feats, [props])
    dets = rh.inference(box["cls_logits"], box["deltas"], [props], [size])[0]
    stored = Detections(g["det_boxes_resized"], g["det_scores_resized"], g["det_classes_resized"].long())
    with_masks = rh.predict_masks(feats, [stored])[0]
    masks = decode_rle(g)
    comb = model.cfg.combine
    seg = combine(masks, g["inst_scores"], g["inst_classes"].long(), g["sem_seg_argmax"].long(),
                  comb.overlap_thresh, comb.stuff_area_limit, comb.instances_confidence_thresh,
                  boxes=g["inst_boxes"])
    threshold = model.cfg.mask_head.mask_threshold
    pasted = paste_masks(g["mask_probs"][:, 0], g["inst_boxes"], frame, threshold)
    stored.mask_probs = g["mask_probs"][:, 0]
    post = detector_postprocess(stored, size, frame, threshold)
    return {"cls_logits": cls_logits, "deltas": deltas, "dets": dets, "mask_probs": with_masks.mask_probs,
            "pasted": pasted, "postprocessed": post, "stored_masks": masks, "panoptic": seg}


# ------------------------------------------------------------------------------------------------ comparisons
def max_diff(got: torch.Tensor, want: torch.Tensor) -> float:
    return float((got.double() - want.double()).abs().max()) if want.numel() else 0.0


def assert_close(name: str, got: torch.Tensor, want: torch.Tensor, atol: float, rtol: float = RTOL) -> float:
    """``|got - want| <= atol + rtol |want|`` everywhere; returns the max abs difference."""
    assert tuple(got.shape) == tuple(want.shape), f"{name}: shape {tuple(got.shape)} vs {tuple(want.shape)}"
    err = (got.double() - want.double()).abs()
    bad = err > atol + rtol * want.double().abs()
    assert not bool(bad.any()), \
        f"{name}: {int(bad.sum())} values out of tolerance, max abs diff {max_diff(got, want):.3g}"
    return max_diff(got, want)


def match_sets(name: str, got_boxes: torch.Tensor, got_scores: torch.Tensor, want_boxes: torch.Tensor,
               want_scores: torch.Tensor, score_atol: float, got_cls: torch.Tensor | None = None,
               want_cls: torch.Tensor | None = None) -> torch.Tensor:
    """Match two ranked lists as sets: each stored entry to one of ours with the same class, the box within
    ``BOX_PX`` and the score within ``score_atol``.  Ranks may differ only between entries whose stored scores
    are within ``RANK_SWAP``; an entry may be missing only at the cut-off (score within ``RANK_SWAP`` of the last).
    Returns ``index[i]`` = our entry matched to stored entry ``i`` (-1 = dropped at the cut-off)."""
    n, m = int(want_boxes.shape[0]), int(got_boxes.shape[0])
    close = (got_boxes[None, :, :].double() - want_boxes[:, None, :].double()).abs().amax(-1) <= BOX_PX
    close &= (got_scores[None, :].double() - want_scores[:, None].double()).abs() <= score_atol
    if want_cls is not None:
        close &= got_cls[None, :] == want_cls[:, None]
    index = torch.full((n,), -1, dtype=torch.int64)
    used = torch.zeros(m, dtype=torch.bool)
    for i in range(n):
        cand = torch.nonzero(close[i] & ~used).squeeze(1)
        if cand.numel():
            j = int(cand[torch.argmin((cand - i).abs())])  # the nearest rank among equal candidates
            index[i], used[j] = j, True
    ws, gs = want_scores.double(), got_scores.double()
    for i in torch.nonzero(index < 0).squeeze(1).tolist():
        assert ws[i] - ws[-1] < RANK_SWAP, f"{name}: stored entry {i} (score {ws[i]:.6g}) has no match"
    for j in torch.nonzero(~used).squeeze(1).tolist():
        assert gs[j] - gs[-1] < RANK_SWAP, f"{name}: our entry {j} (score {gs[j]:.6g}) matches no stored entry"
    for i, j in enumerate(index.tolist()):
        if j >= 0 and j != i:  # a swap: the stored scores at both ranks are (nearly) tied
            assert abs(float(ws[i] - ws[min(j, n - 1)])) < RANK_SWAP, f"{name}: stored rank {i} is our rank {j}"
    return index


def pixel_agreement(got: torch.Tensor, want: torch.Tensor) -> float:
    assert got.shape == want.shape, f"shape {tuple(got.shape)} vs {tuple(want.shape)}"
    return float((got == want).sum()) / max(want.numel(), 1)


def mask_disagreement(got: torch.Tensor, want: torch.Tensor) -> float:
    """Differing pixels of pasted masks as a fraction of the stored masks' total area."""
    assert got.shape == want.shape, f"shape {tuple(got.shape)} vs {tuple(want.shape)}"
    return float((got != want).sum()) / max(float(want.sum()), 1.0)
