"""The assembled model: input normalisation and padding, pyramid geometry, decoding on given features, the
mapping of network classes to dataset categories, categories and configs."""
from __future__ import annotations

import pytest
import torch

from pvslam_core.types import FeaturePyramid
from pvslam_plugins.segmenters.panoptic_fpn.categories import CategorySet, category_set
from pvslam_plugins.segmenters.panoptic_fpn.config import PanopticFPNConfig, preset, reduced
from pvslam_plugins.segmenters.panoptic_fpn.model import PanopticFPN


def small(**kw) -> PanopticFPN:
    torch.manual_seed(0)
    return PanopticFPN(reduced(num_thing_classes=3, num_sem_classes=12, categories="vkitti2"), **kw)


def image(h: int, w: int, seed: int = 0) -> torch.Tensor:
    return (torch.rand(3, h, w, generator=torch.Generator().manual_seed(seed)) * 255).to(torch.uint8)


def test_preprocess_bgr_normalise_then_pad():
    cfg = preset("coco_r50")
    cfg.input.min_size_test = 0
    model = PanopticFPN(cfg)
    img = image(37, 50)
    batch, sizes, out_sizes = model.preprocess([img])
    assert batch.shape == (1, 3, 64, 64) and sizes == [(37, 50)] and out_sizes == [(37, 50)]
    bgr = img.float()[[2, 1, 0]]
    ref = bgr - torch.tensor([103.530, 116.280, 123.675]).view(3, 1, 1)  # std 1
    assert torch.allclose(batch[0, :, :37, :50], ref)
    assert torch.all(batch[0, :, 37:] == 0) and torch.all(batch[0, :, :, 50:] == 0)  # padded after normalising


def test_preprocess_resize_policy_and_output_size():
    cfg = reduced(3, 12, "vkitti2")
    cfg.input.min_size_test, cfg.input.max_size_test = 64, 100
    model = PanopticFPN(cfg)
    batch, sizes, out_sizes = model.preprocess([image(48, 80)])
    assert sizes == [(60, 100)] and out_sizes == [(48, 80)] and batch.shape[-2:] == (64, 128)
    out = model.segment(image(48, 80))
    assert out.ids.shape == (48, 80) and out.semantic.shape == (48, 80)
    assert out.features.image_sizes == [(60, 100)] and out.features.output_sizes == [(48, 80)]


def test_pyramid_geometry_and_decode_on_given_features():
    model = small()
    imgs = [image(60, 80, 1), image(45, 70, 2)]
    pyr = model.extract(imgs)
    assert list(pyr) == ["p2", "p3", "p4", "p5", "p6"]
    for name, s in zip(pyr, (4, 8, 16, 32, 64)):
        assert pyr.stride(name) == s
        assert pyr[name].shape == (2, 64, -(-64 // s), -(-96 // s))  # padded to 64 x 96
    outs = model.decode(pyr)
    again = model.decode(pyr.replace({k: v.clone() for k, v in pyr.items()}))
    for a, b in zip(outs, again):
        assert torch.equal(a.ids, b.ids) and a.segments == b.segments
    assert [o.ids.shape for o in outs] == [(60, 80), (45, 70)]
    # with equal padding, an image's result does not depend on the other images of the batch (ROI batch indices)
    pair = model.decode(model.extract([imgs[0], image(60, 80, 7)]))
    assert torch.equal(pair[0].ids, outs[0].ids) and pair[0].segments == outs[0].segments
    assert torch.allclose(pair[0].detections.boxes, outs[0].detections.boxes, atol=1e-4)
    with pytest.raises(ValueError, match="level p3 has shape"):
        pyr.replace({k: (v[..., :1] if k == "p3" else v) for k, v in pyr.items()})


def test_network_classes_map_to_dataset_categories():
    """Force the heads: semantic channel 5 everywhere but the top rows (channel 0 = things), class 1 ("Car") with
    score ~1 and full masks -> thing segments of category 13 (PVO trainId of Car), stuff of trainId 5."""
    model = small()
    cfg = model.cfg
    cfg.combine.stuff_area_limit = 50
    with torch.no_grad():
        sem = model.sem_seg_head.predictor
        sem.weight.zero_()
        sem.bias.zero_()
        sem.bias[5] = 10.0
        cls = model.roi_heads.box_predictor.cls_score
        cls.weight.zero_()
        cls.bias.zero_()
        cls.bias[1] = 20.0
        model.roi_heads.box_predictor.bbox_pred.weight.zero_()
        model.roi_heads.box_predictor.bbox_pred.bias.zero_()
        mp = model.roi_heads.mask_head.predictor
        mp.weight.zero_()
        mp.bias.fill_(10.0)
    out = model.segment(image(64, 96, 3))
    things = [s for s in out.segments if s.isthing]
    stuff = [s for s in out.segments if not s.isthing]
    assert things and all(s.category_id == 13 and s.score > 0.99 for s in things)
    assert [s.category_id for s in stuff] in ([5], [])
    assert set(out.detections.classes.tolist()) == {1}
    vk = category_set("vkitti2")
    assert vk.by_id(13).name == "Car" and vk.by_id(5).name == "Building"
    assert vk.is_movable(torch.tensor([s.category_id for s in out.segments])).tolist() == \
        [s.isthing for s in out.segments]
    pan = out.to_panoptic()
    assert torch.equal(pan.ids, out.ids) and isinstance(pan.features, FeaturePyramid)
    assert pan.features.names == ["p2", "p3", "p4", "p5", "p6"]
    assert [pan.features.strides[n] for n in pan.features.names] == [4, 8, 16, 32, 64]
    assert torch.equal(pan.features.maps["p3"], out.features["p3"][0])  # [C, h, w] of this image


def test_category_sets():
    coco = category_set("coco_panoptic")
    assert len(coco.categories) == 133 and coco.num_thing_classes == 80 and coco.num_sem_classes == 54
    assert coco.thing_ids()[:3].tolist() == [1, 2, 3] and coco.thing_ids()[-1] == 90
    assert coco.semantic_ids()[:3].tolist() == [0, 92, 93] and coco.semantic_ids()[-1] == 200
    assert coco.by_id(149).name == "road" and not coco.by_id(149).isthing
    assert coco.ids_of(["person", "car", "truck"]) <= coco.movable and 149 not in coco.movable
    vk = category_set("vkitti2")
    assert vk.num_thing_classes == 3 and vk.num_sem_classes == 12
    assert vk.thing_ids().tolist() == [12, 13, 14] and vk.semantic_ids().tolist() == list(range(12))
    assert vk.movable == frozenset({12, 13, 14})
    assert CategorySet.from_dict(vk.to_dict()) == vk
    assert vk.with_movable(["car"]).movable == frozenset({13})
    with pytest.raises(ValueError, match="no categories named"):
        vk.with_movable(["bicycle"])
    with pytest.raises(ValueError, match="unknown built-in category set"):
        category_set("cityscapes")


def test_config_presets_and_checks():
    assert PanopticFPNConfig().box_head.num_classes == 80 and preset("coco_r50").sem_seg.num_classes == 54
    vk = preset("vkitti2_r50")
    assert (vk.box_head.num_classes, vk.sem_seg.num_classes, vk.input.min_size_test, vk.input.max_size_test) == \
        (3, 12, 375, 1242)
    assert vk.combine == PanopticFPNConfig().combine and vk.rpn == PanopticFPNConfig().rpn
    with pytest.raises(ValueError, match="category set"):
        PanopticFPN(preset("coco_r50"), category_set("vkitti2"))
    with pytest.raises(ValueError, match="BasicBlock"):
        PanopticFPNConfig(resnet={"depth": 18})  # res2_out_channels 256 != stem 64
    with pytest.raises(ValueError):
        PanopticFPNConfig(rpn={"nms_thresh": 0.7, "typo": 1})
