"""Every stored tensor of ``panoptic_fpn_golden.pt`` (detectron2's PanopticFPN R-50-FPN on seeded weights, a KITTI
and a synthetic frame) reproduced, stage by stage and end to end, by the ``coco_r50`` model whose weights are
loaded the way a user's ``model_final_*.pkl`` is: a detectron2-style pickle through the segmenter's ``build_model``.

One model build per module and one recorded run per image (``case``): the heavy tensors are computed once.
"""
from __future__ import annotations

import json

import pytest
import torch

from pvslam_plugins.segmenters.panoptic_fpn.checkpoint import read_weights
from pvslam_plugins.segmenters.panoptic_fpn.segmenter import PanopticFPNSegmenterConfig, build_model

from _golden_d2 import (
    ATOL_DENSE,
    ATOL_ROI,
    BOX_PX,
    CFG_CHANGES,
    PIXEL_AGREEMENT,
    assert_close,
    crop,
    golden_state_dict,
    mask_disagreement,
    match_sets,
    pixel_agreement,
    run_image,
    write_model_zoo_pkl,
)

IMAGES = ("kitti", "synth")
LEVELS = ("res2", "res3", "res4", "res5", "p2", "p3", "p4", "p5", "p6")
RPN_LEVELS = ("p2", "p3", "p4", "p5", "p6")


@pytest.fixture(scope="module")
def one_thread():
    """One intra-op torch thread for the module's runs (restored after): CI runs two test workers on two cores,
    and a second thread per worker then only waits for a core."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def golden(fixtures_dir):
    return torch.load(fixtures_dir / "panoptic_fpn_golden.pt", map_location="cpu", weights_only=True)


@pytest.fixture(scope="module")
def pkl_path(golden, tmp_path_factory):
    return write_model_zoo_pkl(golden_state_dict(golden), tmp_path_factory.mktemp("d2") / "model_final_golden.pkl")


@pytest.fixture(scope="module")
def model(pkl_path, one_thread):
    return build_model(PanopticFPNSegmenterConfig(preset="coco_r50", weights=str(pkl_path), **CFG_CHANGES))


@pytest.fixture(scope="module", params=IMAGES)
def case(request, golden, model):
    """``(stored tensors of one image, this model's recorded run on it)``."""
    g = golden[request.param]
    return g, run_image(model, g)


# --------------------------------------------------------------------------------------------------- weights
def test_pickle_loads_every_tensor_exactly(golden, pkl_path, model):
    assert read_weights(pkl_path).kind == "detectron2-pkl"
    want = golden_state_dict(golden)
    got = model.state_dict()
    assert list(got) == list(want) == golden["meta"]["state_dict_keys"]  # upstream names, upstream order
    assert all(torch.equal(got[k], want[k]) for k in want)
    assert sum(v.numel() for v in got.values()) == golden["meta"]["num_params"]
    # anchors of a 2 x 3 grid per level: the stored cell anchors shifted by (x s, y s), in (y, x, anchor) order
    grids = model.proposal_generator.anchors([torch.zeros(1, 1, 2, 3)] * len(RPN_LEVELS))
    for level, anchors in zip(RPN_LEVELS, grids):
        s = golden["meta"]["strides"][level]
        shifts = torch.tensor([[x * s, y * s, x * s, y * s] for y in range(2) for x in range(3)], dtype=torch.float32)
        want = (shifts[:, None, :] + golden["cell_anchors"][level][None]).reshape(-1, 4)
        assert torch.equal(anchors, want), level
    assert torch.equal(model.pixel_mean.flatten(), golden["pixel_mean"].flatten().float())
    assert torch.equal(model.pixel_std.flatten(), golden["pixel_std"].flatten().float())
    cfg = model.cfg
    assert (cfg.box_head.num_classes, cfg.sem_seg.num_classes) == (80, 54)
    assert (cfg.box_head.score_thresh_test, cfg.combine.instances_confidence_thresh,
            cfg.combine.stuff_area_limit) == (0.25, 0.27, 1024)


# ----------------------------------------------------------------------------------------- dense, end to end
def test_input_tensor(case):
    g, run = case
    batch, (size,) = run["batch"], run["sizes"]
    assert list(size) == g["resized_hw"] and list(batch.shape[-2:]) == g["padded_hw"]
    assert list(batch.shape) == g["input_tensor_shape"].tolist()
    assert torch.equal(batch[0, :, -64:, -64:], g["input_tensor_crop"])
    assert float(batch.double().sum()) == pytest.approx(float(g["input_tensor_sum"]), abs=1e-3)


def test_test_time_resize_of_the_stored_frames(golden, model):
    """From the frames themselves: the resize policy gives detectron2's sizes, and the bilinear resize agrees with
    PIL's (which made the stored input) to one grey level."""
    for name in IMAGES:
        g = golden[name]
        if name == "kitti":
            frame, want = g["image_gray_uint8"][None].repeat(3, 1, 1), g["model_input_gray_uint8"][None].float()
        else:
            frame, want = g["image_bgr_uint8"].permute(2, 0, 1).flip(0), g["model_input_uint8"].float()
        batch, (size,), (out_size,) = model.preprocess([frame])
        assert list(size) == g["resized_hw"] and list(batch.shape[-2:]) == g["padded_hw"]
        assert out_size == (g["height"], g["width"])
        h, w = size
        got = batch[0, :, :h, :w] + model.pixel_mean  # back to 0..255 (pixel_std is 1)
        assert float((got - want).abs().max()) <= 1.0 + 1e-4, name


def test_backbone_and_fpn(case, golden):
    g, run = case
    maps = {**run["res"], **run["pyramid"].levels}
    for name in LEVELS:
        x, stride = maps[name][0], golden["meta"]["strides"][name]
        want = g["features"]
        assert list(x.shape) == want[f"{name}_shape"].tolist(), name
        assert_close(f"{name}_crop", crop(x, stride), want[f"{name}_crop"], ATOL_DENSE)
        assert_close(f"{name}_chmean", x.mean(dim=(1, 2)), want[f"{name}_chmean"], ATOL_DENSE)
        assert_close(f"{name}_spmean", x.mean(dim=0), want[f"{name}_spmean"], ATOL_DENSE)


def test_rpn_head(case, golden):
    g, run = case
    logits, deltas = run["rpn_head"]
    for i, level in enumerate(RPN_LEVELS):
        stride, want = golden["meta"]["strides"][level], g["rpn"]
        assert_close(f"objectness_{level}", logits[i][0], want[f"objectness_{level}"], ATOL_DENSE)
        d = deltas[i][0]
        assert list(d.shape) == want[f"deltas_{level}_shape"].tolist()
        assert_close(f"deltas_{level}_crop", crop(d, stride), want[f"deltas_{level}_crop"], ATOL_DENSE)
        # the whole map, through its sum: within the per-value tolerance summed over every value
        assert abs(float(d.double().sum() - want[f"deltas_{level}_sum"].double())) <= ATOL_DENSE * d.numel()


def test_proposals(case):
    g, run = case
    props, want_boxes, want_logits = run["proposals"], g["rpn"]["proposal_boxes"], g["rpn"]["proposal_logits"]
    assert props.boxes.shape == want_boxes.shape
    index = match_sets("proposals", props.boxes, props.logits, want_boxes, want_logits, ATOL_DENSE)
    hit = index >= 0
    assert_close("proposal_logits", props.logits[index[hit]], want_logits[hit], ATOL_DENSE)


def test_semantic_head(case):
    g, run = case
    s4, padded, out = run["sem_stride4"], run["sem_padded"], run["sem_out"]
    assert list(s4.shape) == g["sem_seg_logits_stride4_shape"].tolist()
    assert_close("stride4_crop", crop(s4, 4), g["sem_seg_logits_stride4_crop"], ATOL_DENSE)
    assert_close("stride4_chmean", s4.mean(dim=(1, 2)), g["sem_seg_logits_stride4_chmean"], ATOL_DENSE)
    assert list(padded.shape) == g["sem_seg_logits_padded_shape"].tolist()
    assert_close("padded_crop", padded[:, -32:, -32:], g["sem_seg_logits_padded_crop"], ATOL_DENSE)
    assert out.shape[1:] == (g["height"], g["width"])
    assert_close("out_crop", out[:, -32:, -32:], g["sem_seg_out_crop"], ATOL_DENSE)
    assert_close("out_topleft", out[:, :16, :16], g["sem_seg_out_topleft"], ATOL_DENSE)
    assert_close("out_chmean", out.mean(dim=(1, 2)), g["sem_seg_out_chmean"], ATOL_DENSE)
    assert pixel_agreement(out.argmax(0), g["sem_seg_argmax"].long()) >= PIXEL_AGREEMENT


# ------------------------------------------------------------------------------ stages from the stored inputs
def test_box_head_from_stored_proposals(case):
    g, run = case
    st, want = run["stage"], g["box"]
    assert_close("pooled_first4", st["box_pooled_first4"], want["pooled_first4"], ATOL_ROI)
    assert_close("box_head_features_first16", st["box_features_first16"], want["box_head_features_first16"],
                 ATOL_ROI)
    assert_close("cls_logits", st["cls_logits"], want["cls_logits"], ATOL_ROI)
    assert_close("deltas", st["deltas"], want["deltas"], ATOL_ROI)


def test_detections_from_stored_box_outputs(case):
    g, run = case
    d = run["stage"]["dets"]
    want_boxes, want_scores = g["det_boxes_resized"], g["det_scores_resized"]
    assert len(d) == want_boxes.shape[0] and len(d) > 0
    index = match_sets("detections", d.boxes, d.scores, want_boxes, want_scores, ATOL_ROI,
                       d.classes, g["det_classes_resized"].long())
    hit = index >= 0
    assert_close("det_boxes_resized", d.boxes[index[hit]], want_boxes[hit], 1e-2, 0.0)
    assert_close("det_scores_resized", d.scores[index[hit]], want_scores[hit], ATOL_ROI)


def test_mask_head_from_stored_detections(case):
    g, run = case
    st = run["stage"]
    assert_close("mask_pooled_first2", st["mask_pooled_first2"], g["mask_pooled_first2"], ATOL_ROI)
    assert_close("mask_probs", st["mask_probs"], g["mask_probs"][:, 0], ATOL_ROI)


def test_pasted_masks_from_stored_probabilities(case):
    g, run = case
    pasted, stored = run["stage"]["pasted"], run["stage"]["stored_masks"]
    assert torch.equal(stored.sum(dim=(1, 2)), g["inst_masks_area"].long())  # the RLE decodes as documented
    assert mask_disagreement(pasted, stored) <= 1.0 - PIXEL_AGREEMENT
    post = run["stage"]["postprocessed"]  # the stored detections rescaled to the frame, then pasted
    assert_close("inst_boxes", post.boxes, g["inst_boxes"], BOX_PX, 0.0)
    assert torch.equal(post.scores, g["inst_scores"]) and torch.equal(post.classes, g["inst_classes"].long())
    assert mask_disagreement(post.masks, stored) <= 1.0 - PIXEL_AGREEMENT


def _check_segments(g, isthing, labels, areas, scores, instances=None) -> None:
    """The stored ``segments_info`` (contiguous ids); stuff areas within the panoptic map's pixel tolerance."""
    want = json.loads(g["segments_info_json"])
    area_tol = (1.0 - PIXEL_AGREEMENT) * int(g["height"]) * int(g["width"])
    assert [s["id"] for s in want] == list(range(1, len(isthing) + 1))
    assert [s["isthing"] for s in want] == list(isthing)
    assert [s["category_id"] for s in want] == list(labels)
    for s, area, score in zip(want, areas, scores):
        if s["isthing"]:
            assert score == pytest.approx(s["score"], abs=ATOL_ROI)
        else:
            assert abs(area - s["area"]) <= area_tol
    if instances is not None:
        assert [s.get("instance_id", -1) for s in want] == list(instances)


def test_panoptic_from_stored_inputs(case):
    g, run = case
    seg = run["stage"]["panoptic"]
    assert pixel_agreement(seg.ids, g["panoptic_seg"].long()) >= PIXEL_AGREEMENT
    _check_segments(g, seg.isthing, seg.labels, seg.areas, seg.scores, seg.instances)


# ---------------------------------------------------------------------------------------- final, end to end
def test_end_to_end_panoptic_from_model_input(case, model):
    g, run = case
    out = run["out"]
    d = out.detections
    index = match_sets("instances", d.boxes, d.scores, g["inst_boxes"], g["inst_scores"], ATOL_ROI,
                       d.classes, g["inst_classes"].long())
    assert bool((index >= 0).all()) and len(d) == g["inst_boxes"].shape[0]  # the instance lists match
    assert mask_disagreement(d.masks[index], run["stage"]["stored_masks"]) <= 1.0 - PIXEL_AGREEMENT
    assert pixel_agreement(out.semantic, g["sem_seg_argmax"].long()) >= PIXEL_AGREEMENT
    assert pixel_agreement(out.ids, g["panoptic_seg"].long()) >= PIXEL_AGREEMENT
    # segments carry dataset ids: map the stored contiguous ids through the model's category set
    things, stuff = model.categories.thing_ids().tolist(), model.categories.semantic_ids().tolist()
    want = json.loads(g["segments_info_json"])
    assert [s.id for s in out.segments] == [s["id"] for s in want]
    assert [s.category_id for s in out.segments] == [
        things[s["category_id"]] if s["isthing"] else stuff[s["category_id"]] for s in want]
    areas = [int((out.ids == s.id).sum()) for s in out.segments]
    _check_segments(g, [s.isthing for s in out.segments], [s["category_id"] for s in want], areas,
                    [s.score for s in out.segments])
