"""Safe, strict checkpoint loading: detectron2 .pkl (restricted unpickler), .pth (weights_only), pvslam's format.

The COCO key table below is written from reference/checkpoints.md §2.3 (not from the model code), so a naming
or shape slip in the model fails here."""
from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from pvslam_plugins.segmenters.panoptic_fpn.categories import category_set
from pvslam_plugins.segmenters.panoptic_fpn.checkpoint import (
    CheckpointError,
    CheckpointMismatch,
    UnsafeCheckpoint,
    load_checkpoint,
    load_weights,
    read_weights,
    save_checkpoint,
)
from pvslam_plugins.segmenters.panoptic_fpn.config import preset, reduced
from pvslam_plugins.segmenters.panoptic_fpn.model import PanopticFPN


# --------------------------------------------------------------------------------------- documented key table
def detectron2_keys(num_things: int = 80, num_sem: int = 54) -> dict[str, tuple[int, ...]]:
    """checkpoints.md §2.3: name -> shape of detectron2's PanopticFPN R-50-FPN state_dict."""
    keys: dict[str, tuple[int, ...]] = {}

    def conv_norm(prefix: str, shape: tuple[int, ...]) -> None:
        keys[f"{prefix}.weight"] = shape
        for s in ("weight", "bias", "running_mean", "running_var"):
            keys[f"{prefix}.norm.{s}"] = (shape[0],)

    bu = "backbone.bottom_up"
    conv_norm(f"{bu}.stem.conv1", (64, 3, 7, 7))
    for name, blocks, mid, out, cin in (("res2", 3, 64, 256, 64), ("res3", 4, 128, 512, 256),
                                        ("res4", 6, 256, 1024, 512), ("res5", 3, 512, 2048, 1024)):
        for i in range(blocks):
            p = f"{bu}.{name}.{i}"
            if i == 0:
                conv_norm(f"{p}.shortcut", (out, cin, 1, 1))
            conv_norm(f"{p}.conv1", (mid, cin if i == 0 else out, 1, 1))
            conv_norm(f"{p}.conv2", (mid, mid, 3, 3))
            conv_norm(f"{p}.conv3", (out, mid, 1, 1))
    for lvl, c in zip((2, 3, 4, 5), (256, 512, 1024, 2048)):
        keys[f"backbone.fpn_lateral{lvl}.weight"] = (256, c, 1, 1)
        keys[f"backbone.fpn_lateral{lvl}.bias"] = (256,)
        keys[f"backbone.fpn_output{lvl}.weight"] = (256, 256, 3, 3)
        keys[f"backbone.fpn_output{lvl}.bias"] = (256,)
    rpn = "proposal_generator.rpn_head"
    keys.update({f"{rpn}.conv.weight": (256, 256, 3, 3), f"{rpn}.conv.bias": (256,),
                 f"{rpn}.objectness_logits.weight": (3, 256, 1, 1), f"{rpn}.objectness_logits.bias": (3,),
                 f"{rpn}.anchor_deltas.weight": (12, 256, 1, 1), f"{rpn}.anchor_deltas.bias": (12,)})
    keys.update({"roi_heads.box_head.fc1.weight": (1024, 12544), "roi_heads.box_head.fc1.bias": (1024,),
                 "roi_heads.box_head.fc2.weight": (1024, 1024), "roi_heads.box_head.fc2.bias": (1024,),
                 "roi_heads.box_predictor.cls_score.weight": (num_things + 1, 1024),
                 "roi_heads.box_predictor.cls_score.bias": (num_things + 1,),
                 "roi_heads.box_predictor.bbox_pred.weight": (4 * num_things, 1024),
                 "roi_heads.box_predictor.bbox_pred.bias": (4 * num_things,)})
    for k in range(1, 5):
        keys[f"roi_heads.mask_head.mask_fcn{k}.weight"] = (256, 256, 3, 3)
        keys[f"roi_heads.mask_head.mask_fcn{k}.bias"] = (256,)
    keys.update({"roi_heads.mask_head.deconv.weight": (256, 256, 2, 2), "roi_heads.mask_head.deconv.bias": (256,),
                 "roi_heads.mask_head.predictor.weight": (num_things, 256, 1, 1),
                 "roi_heads.mask_head.predictor.bias": (num_things,)})
    for head, convs in (("p2", (0,)), ("p3", (0,)), ("p4", (0, 2)), ("p5", (0, 2, 4))):
        for j in convs:
            p = f"sem_seg_head.{head}.{j}"
            keys[f"{p}.weight"] = (128, 256 if j == 0 else 128, 3, 3)
            keys[f"{p}.norm.weight"] = (128,)
            keys[f"{p}.norm.bias"] = (128,)
    keys["sem_seg_head.predictor.weight"] = (num_sem, 128, 1, 1)
    keys["sem_seg_head.predictor.bias"] = (num_sem,)
    return keys


def random_weights(keys: dict[str, tuple[int, ...]], seed: int = 0) -> dict[str, np.ndarray]:
    """Plausible float32 values: He-scaled conv/fc weights, BN stats near the identity."""
    rng = np.random.default_rng(seed)
    out = {}
    for k, shape in keys.items():
        if k.endswith("running_var"):
            v = rng.uniform(0.5, 1.5, shape)
        elif k.endswith("norm.weight"):
            v = rng.uniform(0.2, 0.6, shape)
        elif k.endswith("bias") or k.endswith("running_mean"):
            v = rng.normal(0, 0.05, shape)
        else:
            fan = int(np.prod(shape[1:])) if len(shape) > 1 else 1
            v = (rng.random(shape, dtype=np.float32) - 0.5) * np.float32(np.sqrt(12.0 / fan))  # unit gain
        out[k] = v.astype(np.float32)
    return out


@pytest.fixture(scope="module")
def coco_pkl(tmp_path_factory) -> tuple[Path, dict[str, np.ndarray]]:
    keys = detectron2_keys()
    assert len(keys) == 330  # checkpoints.md: 330 keys for COCO
    assert sum(int(np.prod(s)) for s in keys.values()) == 46_080_230  # and 46,080,230 values
    weights = random_weights(keys)
    model = dict(weights)
    for i in range(5):  # 2019 files may carry the anchors as buffers; detectron2 ignores them
        model[f"proposal_generator.anchor_generator.cell_anchors.{i}"] = np.zeros((3, 4), np.float32)
    path = tmp_path_factory.mktemp("ckpt") / "model_final_test.pkl"
    with open(path, "wb") as f:
        pickle.dump({"model": model, "__author__": "Detectron2 Model Zoo"}, f, protocol=4)  # 2: see below
    return path, weights


# ------------------------------------------------------------------------------------------------- detectron2
def test_coco_pkl_loads_strictly_and_runs(coco_pkl):
    path, weights = coco_pkl
    cfg = preset("coco_r50")
    cfg.input.min_size_test = 0  # keep the test image small (the real policy resizes to 800)
    cfg.box_head.detections_per_image = 8  # random weights detect ~100 boxes; the mask head is the cost
    model = PanopticFPN(cfg)
    assert sorted(model.state_dict()) == sorted(weights)
    report = load_weights(model, path)
    assert report.ok and report.loaded == 330 and not report.filled
    assert len(report.ignored) == 5 and all("cell_anchors" in k for k in report.ignored)
    sd = model.state_dict()
    for k in ("backbone.bottom_up.res4.5.conv3.norm.running_var", "roi_heads.box_head.fc1.weight",
              "sem_seg_head.p5.4.weight", "proposal_generator.rpn_head.anchor_deltas.bias"):
        assert torch.equal(sd[k], torch.from_numpy(weights[k])), k

    g = torch.Generator().manual_seed(0)
    img = (torch.rand(3, 96, 128, generator=g) * 255).to(torch.uint8)
    out = model.segment(img)
    assert out.ids.shape == (96, 128) and out.ids.dtype == torch.int64
    present = set(out.ids.unique().tolist()) - {0}
    assert present == {s.id for s in out.segments}  # every segment has pixels, every id has a segment
    coco_ids = {c.id: c for c in category_set("coco_panoptic").categories}
    for s in out.segments:
        assert coco_ids[s.category_id].isthing == s.isthing
        if not s.isthing:
            assert int((out.ids == s.id).sum()) >= 4096
    assert [k for k in out.features] == ["p2", "p3", "p4", "p5", "p6"]
    assert out.features["p2"].shape == (1, 256, 24, 32) and out.features.stride("p6") == 64


def test_malicious_pickle_is_refused(tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    path = tmp_path / "evil.pkl"
    with open(path, "wb") as f:
        pickle.dump({"model": {"w": Evil()}, "__author__": "Detectron2 Model Zoo"}, f)
    with pytest.raises(UnsafeCheckpoint, match=r"refusing to unpickle global '(posix|os|nt)\.system'"):
        read_weights(path)
    assert not marker.exists()
    # protocol 0 text pickle calling builtins.eval
    path.write_bytes(b"c__builtin__\neval\n(S'1+1'\ntR.")
    with pytest.raises(UnsafeCheckpoint, match=r"__builtin__\.eval"):
        read_weights(path)
    # a torch tensor inside a .pkl needs torch's rebuild functions: refused too
    with open(path, "wb") as f:
        pickle.dump({"model": {"w": torch.zeros(2)}, "__author__": "x"}, f)
    with pytest.raises(UnsafeCheckpoint, match=r"torch"):
        read_weights(path)


@pytest.mark.parametrize("protocol", [2, 4])
def test_small_pkl_with_numpy_arrays(tmp_path, protocol):
    """Arrays of several dtypes round-trip; missing FrozenBN statistics are filled as detectron2 does for .pkl."""
    cfg = reduced()
    cfg.resnet.norm = "FrozenBN"
    from pvslam_plugins.segmenters.panoptic_fpn.categories import CategorySet
    from pvslam_core.types import Category

    cats = CategorySet("t", tuple([Category(i + 1, f"s{i}", False) for i in range(10)]
                                  + [Category(20 + i, f"t{i}", True) for i in range(3)]))
    model = PanopticFPN(cfg, cats)
    sd = {k: v.numpy().copy() for k, v in model.state_dict().items()}
    sd = {k: (v * 0 + 0.5 if k.endswith("running_var") else v) for k, v in sd.items()}
    dropped = "backbone.bottom_up.res3.0.conv1.norm.running_mean"
    del sd[dropped]
    sd["backbone.fpn_lateral2.bias"] = sd["backbone.fpn_lateral2.bias"].astype(np.float64)  # cast on load
    path = tmp_path / "small.pkl"
    with open(path, "wb") as f:
        pickle.dump({"model": sd, "__author__": "test", "matching_heuristics": False}, f, protocol=protocol)
    wf = read_weights(path)
    assert wf.kind == "detectron2-pkl" and wf.state_dict["backbone.fpn_lateral2.bias"].dtype == torch.float64
    fresh = PanopticFPN(cfg, cats)
    report = load_weights(fresh, path)
    assert report.filled == [dropped]
    got = fresh.state_dict()
    assert torch.equal(got[dropped], torch.zeros_like(got[dropped]))
    assert torch.all(got["backbone.bottom_up.res2.0.conv1.norm.running_var"] == 0.5)
    assert got["backbone.fpn_lateral2.bias"].dtype == torch.float32


def test_matching_heuristics_and_caffe2_files_are_rejected(tmp_path):
    path = tmp_path / "r50.pkl"
    with open(path, "wb") as f:
        pickle.dump({"model": {}, "__author__": "torchvision", "matching_heuristics": True}, f)
    with pytest.raises(CheckpointError, match="matching_heuristics"):
        read_weights(path)
    with open(path, "wb") as f:
        pickle.dump({"blobs": {"conv1_w": np.zeros(1)}}, f)
    with pytest.raises(CheckpointError, match="Caffe2"):
        read_weights(path)


# ------------------------------------------------------------------------------------------------------ .pth
def _small_model() -> PanopticFPN:
    return PanopticFPN(reduced(num_thing_classes=3, num_sem_classes=12, categories="vkitti2"))


def test_mismatch_report_names_every_problem(tmp_path):
    model = _small_model()
    sd = model.state_dict()
    del sd["sem_seg_head.predictor.bias"]
    sd["roi_heads.box_head.fc3.weight"] = torch.zeros(2, 2)
    sd["roi_heads.box_predictor.cls_score.weight"] = torch.zeros(81, 256)
    path = tmp_path / "bad.pth"
    torch.save({"model": sd}, path)
    with pytest.raises(CheckpointMismatch) as e:
        load_weights(_small_model(), path)
    msg = str(e.value)
    assert "missing in the file (1)" in msg and "sem_seg_head.predictor.bias" in msg
    assert "unexpected in the file (1)" in msg and "roi_heads.box_head.fc3.weight" in msg
    assert "roi_heads.box_predictor.cls_score.weight: [81, 256] vs [4, 256]" in msg
    r = e.value.report
    assert r.missing == ["sem_seg_head.predictor.bias"] and r.unexpected == ["roi_heads.box_head.fc3.weight"]
    # strict=False loads what matches and returns the same report
    assert not load_weights(_small_model(), path, strict=False).ok


def test_pvo_style_pth(tmp_path):
    """PVO's VKITTI2 layout: 3 things, 12 semantic channels, fusion_conv1 (kept for the VPS head), fvcore's
    'model' wrapper with a 'module.' prefix, persistent pixel_mean/std buffers, BN num_batches_tracked."""
    keys = detectron2_keys(num_things=3, num_sem=12)
    assert len(keys) == 330
    keys["fusion_conv1.weight"] = (256, 512, 3, 3)
    keys["fusion_conv1.bias"] = (256,)
    sd = {f"module.{k}": torch.from_numpy(v) for k, v in random_weights(keys, seed=1).items()}
    sd["module.pixel_mean"] = torch.tensor([103.53, 116.28, 123.675]).view(3, 1, 1) + 1.0
    sd["module.pixel_std"] = torch.ones(3, 1, 1)
    sd["module.backbone.bottom_up.stem.conv1.norm.num_batches_tracked"] = torch.tensor(0)
    path = tmp_path / "panFPN.pth"
    torch.save({"model": sd, "iteration": 270000, "optimizer": {"state": {}, "param_groups": []}}, path)
    model = PanopticFPN(preset("vkitti2_r50"))
    report = load_weights(model, path)
    assert report.ok and report.loaded == 330 + 2  # + pixel_mean/std
    assert sorted(report.extra) == ["fusion_conv1.bias", "fusion_conv1.weight"]
    assert report.extra["fusion_conv1.weight"].shape == (256, 512, 3, 3)
    assert torch.allclose(model.pixel_mean.flatten(), torch.tensor([104.53, 117.28, 124.675]))
    assert report.ignored == ["backbone.bottom_up.stem.conv1.norm.num_batches_tracked"]
    assert torch.equal(model.state_dict()["roi_heads.mask_head.predictor.bias"],
                       sd["module.roi_heads.mask_head.predictor.bias"])


def test_unsafe_pth_is_refused(tmp_path):
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return os.system, (f"touch {marker}",)

    path = tmp_path / "evil.pth"
    torch.save({"model": {"w": torch.zeros(1)}, "x": Evil()}, path)
    with pytest.raises(UnsafeCheckpoint, match="weights_only"):
        read_weights(path)
    assert not marker.exists()


# ------------------------------------------------------------------------------------------------ own format
def test_own_checkpoint_round_trip(tmp_path):
    torch.manual_seed(0)
    model = _small_model()
    path = tmp_path / "seg.pt"
    save_checkpoint(model, path)
    back = load_checkpoint(path)
    assert back.cfg == model.cfg and back.categories == model.categories
    img = (torch.rand(3, 64, 80) * 255).to(torch.uint8)
    a, b = model.segment(img), back.segment(img)
    assert torch.equal(a.ids, b.ids) and a.segments == b.segments
    for k in a.features:
        assert torch.equal(a.features[k], b.features[k])
    with pytest.raises(CheckpointError, match="not a pvslam PanopticFPN checkpoint"):
        torch.save({"model": model.state_dict()}, tmp_path / "plain.pth")
        load_checkpoint(tmp_path / "plain.pth")
    # float16 storage (the shipped file): half the size, loads back to float32 tensors equal to the rounded ones
    save_checkpoint(model, tmp_path / "half.pt", dtype=torch.float16)
    half = load_checkpoint(tmp_path / "half.pt")
    assert (tmp_path / "half.pt").stat().st_size < 0.6 * path.stat().st_size
    for k, v in model.state_dict().items():
        got = half.state_dict()[k]
        assert got.dtype == v.dtype and torch.equal(got, v.half().to(v.dtype) if v.is_floating_point() else v), k
