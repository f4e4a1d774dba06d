"""Per-stage CPU timing of PanopticFPN forwards (random weights), for the benchmark notes.

    python -m pvslam_plugins.segmenters.panoptic_fpn.timing --preset reduced --size 320x240 --threads 2
    python -m pvslam_plugins.segmenters.panoptic_fpn.timing --preset coco_r50 --size 1226x370 --worst-case

Random weights make the ROI work arbitrary, so the script prints how many proposals and detections survived;
``--worst-case`` zeroes the box deltas (proposals = anchors, detections = proposals), disables RPN NMS
(post_nms_topk proposals survive) and the score threshold (detections_per_image detections reach the mask
head): the most ROI work the configuration allows.
Wall time is shared-machine sensitive: the CPU time of the process is printed next to it.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from .categories import BUILTIN_SETS, CategorySet
from .config import preset
from .model import PanopticFPN
from .ops import apply_deltas
from .panoptic import argmax_channels, combine, detector_postprocess, semantic_postprocess


def profile(model: PanopticFPN, img: torch.Tensor, reps: int = 3) -> dict[str, float]:
    """Median milliseconds per stage over ``reps`` runs (after one warm-up), plus counts of the last run."""
    stages: dict[str, list[float]] = {}

    def tick(name: str, t0: float) -> float:
        t1 = time.perf_counter()
        stages.setdefault(name, []).append((t1 - t0) * 1e3)
        return t1

    counts = {}
    cpu0 = time.process_time()
    wall0 = time.perf_counter()
    with torch.no_grad():
        for rep in range(reps + 1):
            if rep == 1:
                stages.clear()
                cpu0, wall0 = time.process_time(), time.perf_counter()
            t = time.perf_counter()
            pyr = model.extract([img])
            t = tick("backbone+fpn", t)
            sem = model.semantic_logits(pyr)
            t = tick("semantic head", t)
            props = model.propose(pyr)
            t = tick("rpn", t)
            feats = pyr.select(("p2", "p3", "p4", "p5"))
            logits, deltas = model.roi_heads.box_outputs(feats, [p.boxes for p in props])
            boxes = apply_deltas(deltas, props[0].boxes, model.cfg.box_head.bbox_reg_weights)
            dets = [model.roi_heads.select_boxes(boxes, logits.softmax(-1), pyr.image_sizes[0])]
            t = tick("box head", t)
            dets = model.roi_heads.predict_masks(feats, dets)
            t = tick("mask head", t)
            comb = model.cfg.combine
            logits = semantic_postprocess(sem[0], pyr.image_sizes[0], pyr.output_sizes[0])
            labels, label_probs = argmax_channels(logits)
            d = detector_postprocess(dets[0], pyr.image_sizes[0], pyr.output_sizes[0])
            seg = combine(d.masks, d.scores, d.classes, labels, comb.overlap_thresh,
                          comb.stuff_area_limit, comb.instances_confidence_thresh, label_probs, d.boxes)
            tick("paste+combine", t)
            counts = {"proposals": len(props[0].boxes), "detections": len(dets[0]), "segments": len(seg.labels)}
    out = {k: statistics.median(v) for k, v in stages.items()}
    out["total"] = sum(out.values())
    out["cpu_ms_per_run"] = (time.process_time() - cpu0) * 1e3 / reps
    out["wall_ms_per_run"] = (time.perf_counter() - wall0) * 1e3 / reps
    out.update(counts)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="reduced")
    ap.add_argument("--size", default="320x240", help="WxH of the frame")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--resize", action="store_true", help="keep the preset's test resize (default: native size)")
    ap.add_argument("--worst-case", action="store_true")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = preset(args.preset)
    if not args.resize:
        cfg.input.min_size_test = 0
    if args.worst_case:
        cfg.rpn.nms_thresh = 1.0
        cfg.box_head.score_thresh_test = 0.0
    cats = None
    if cfg.categories not in BUILTIN_SETS:
        cats = CategorySet.placeholder(cfg.box_head.num_classes, cfg.sem_seg.num_classes, cfg.categories)
    model = PanopticFPN(cfg, cats).to(args.device)
    if args.worst_case:  # random weights send most boxes off the image: make proposals = anchors, boxes = proposals
        with torch.no_grad():
            for layer in (model.proposal_generator.rpn_head.anchor_deltas, model.roi_heads.box_predictor.bbox_pred):
                layer.weight.zero_()
                layer.bias.zero_()
    w, h = (int(v) for v in args.size.lower().split("x"))
    img = (torch.rand(3, h, w) * 255).to(torch.uint8)
    res = profile(model, img.to(args.device), args.reps)
    print(f"{args.preset} {w}x{h} threads={args.threads} worst_case={args.worst_case} "
          f"params={sum(p.numel() for p in model.parameters()) / 1e6:.2f}M")
    for k, v in res.items():
        print(f"  {k:16s} {v:9.1f}" if isinstance(v, float) else f"  {k:16s} {v:9d}")


if __name__ == "__main__":
    main()
