"""Checkpoint loading: droid.pth-like and PVO-keyed dicts, pvslam's own format, wrong files, unsafe pickles."""
from __future__ import annotations

import pathlib
import pickle
from collections import OrderedDict

import pytest
import torch

from pvslam_plugins.frontends.raft_gru import CheckpointError, RaftGruNet, load_checkpoint, load_model, save_checkpoint
from pvslam_plugins.frontends.raft_gru.checkpoint import FORMAT, check_state_dict, detect_variant

HEADS = ("update.weight.2.weight", "update.weight.2.bias", "update.delta.2.weight", "update.delta.2.bias")


def _droid_pth_like(state_dict: dict, rows: int = 3) -> OrderedDict:
    """What droid.pth looks like: DDP's ``module.`` prefix and extra output rows in the 4 head tensors."""
    g = torch.Generator().manual_seed(7)
    out = OrderedDict()
    for k, v in state_dict.items():
        if k in HEADS:
            v = torch.cat([v, torch.randn((rows - 2,) + v.shape[1:], generator=g)])
        out["module." + k] = v.clone()
    return out


def _assert_same_params(model: torch.nn.Module, state_dict: dict) -> None:
    got = model.state_dict()
    assert sorted(got) == sorted(state_dict)
    assert all(torch.equal(got[k], state_dict[k]) for k in state_dict)


def test_droid_pth_file_loads_strictly_like_droid(tmp_path, droid_golden, droid_features):
    path = tmp_path / "droid.pth"
    torch.save(_droid_pth_like(droid_golden["state_dict"]), path)
    model, ckpt = load_model(path)
    assert (ckpt.variant, ckpt.source, ckpt.use_aff_bri) == ("droid", "droid", False)
    assert sorted(ckpt.notes) == sorted(f"{k}: kept 2 of 3 rows" for k in HEADS)
    _assert_same_params(model, droid_golden["state_dict"])  # the first two rows, everything else unchanged
    assert not model.training
    with torch.no_grad():
        f = model.features(droid_golden["images_uint8"], context=False)
    assert torch.equal(f.fmap, droid_features.fmap)


def test_pvo_keyed_dict_loads_without_slicing(tmp_path, pvo_full_state_dict):
    path = tmp_path / "vkitti2_dy_train_semiv4_080000.pth"
    torch.save({"module." + k: v for k, v in pvo_full_state_dict.items()}, path)
    model, ckpt = load_model(path)
    assert (ckpt.variant, ckpt.source, ckpt.notes) == ("pvo", "pvo", [])
    assert model.variant == "pvo" and model.motion_dim == 8
    _assert_same_params(model, pvo_full_state_dict)


def test_pvo_head_with_extra_rows_is_not_sliced(pvo_full_state_dict):
    sd = dict(pvo_full_state_dict)
    sd["update.delta.2.weight"] = torch.cat([sd["update.delta.2.weight"], sd["update.delta.2.weight"][:1]])
    msg = r"update\.delta\.2\.weight: expected \(2, 128, 3, 3\), got \(3, 128, 3, 3\)"
    with pytest.raises(CheckpointError, match=msg):
        load_model(sd)


def test_variant_detection():
    assert detect_variant(RaftGruNet("droid").state_dict()) == ("droid", False)
    assert detect_variant(RaftGruNet("pvo").state_dict()) == ("pvo", False)
    assert detect_variant(RaftGruNet("pvo", use_aff_bri=True).state_dict()) == ("pvo", True)
    with pytest.raises(CheckpointError, match="no 'update.\\*' keys"):
        detect_variant(["fnet.conv1.weight"])


def test_asked_variant_must_match(droid_golden):
    with pytest.raises(CheckpointError, match="holds a 'droid' network, but variant='pvo' was asked for"):
        load_checkpoint(droid_golden["state_dict"], variant="pvo")


def test_partial_and_wrong_checkpoints_name_keys_and_shapes(droid_golden):
    sd = dict(droid_golden["state_dict"])
    del sd["update.agg.eta.0.weight"]
    sd["update.extra.weight"] = torch.zeros(3)
    sd["update.flow_encoder.0.weight"] = torch.zeros(128, 5, 7, 7)
    with pytest.raises(CheckpointError) as info:
        load_model(sd)
    msg = str(info.value)
    assert "missing keys (1):\n    update.agg.eta.0.weight" in msg
    assert "unexpected keys (1):\n    update.extra.weight" in msg
    assert "shape mismatches (1):\n    update.flow_encoder.0.weight: expected (128, 4, 7, 7), got (128, 5, 7, 7)" in msg


def test_error_lists_are_truncated(droid_golden):
    sd = {k: v for k, v in droid_golden["state_dict"].items() if not k.startswith("cnet.")}  # 32 keys missing
    with pytest.raises(CheckpointError) as info:
        check_state_dict(RaftGruNet("droid"), sd, "partial.pth")
    msg = str(info.value)
    assert msg.startswith("partial.pth does not fit RaftGruNet(variant='droid'):")
    assert "missing keys (32):" in msg and "... and 20 more" in msg and msg.count("\n    cnet.") == 12


def test_droid_checkpoint_into_pvo_model_is_explained(droid_golden):
    with pytest.raises(CheckpointError) as info:
        check_state_dict(RaftGruNet("pvo"), droid_golden["state_dict"], "droid.pth")
    msg = str(info.value)
    assert "update.agg.upmask_disp.0.weight" in msg and "update.agg.upmask.0.weight" in msg
    assert "update.flow_encoder.0.weight: expected (128, 8, 7, 7), got (128, 4, 7, 7)" in msg


def test_not_a_state_dict(tmp_path):
    with pytest.raises(CheckpointError, match=r"these entries are not tensors:\n    step: int"):
        load_checkpoint({"fnet.conv1.weight": torch.zeros(1), "step": 3})
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        load_checkpoint(tmp_path / "missing.pth")
    bad = tmp_path / "garbage.pth"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="garbage.pth"):
        load_checkpoint(bad)


class _Payload:
    """Unpickling this object would create a file: the test proves the loader never runs it."""

    def __init__(self, marker: pathlib.Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


def test_unsafe_pickle_is_refused_and_not_executed(tmp_path, droid_golden):
    marker = tmp_path / "executed"
    path = tmp_path / "evil.pth"
    torch.save({**droid_golden["state_dict"], "payload": _Payload(marker)}, path)
    with pytest.raises(CheckpointError, match="refused - the file holds objects"):
        load_model(path)
    assert not marker.exists()
    # the payload really would run under a plain unpickler, so the test above can fail
    pickle.loads(pickle.dumps(_Payload(marker)))
    assert marker.exists()


def test_own_format_round_trip_with_training_state(tmp_path, droid_golden):
    model = RaftGruNet("droid")
    model.load_state_dict(droid_golden["state_dict"])
    opt = torch.optim.AdamW(model.update.parameters(), lr=1e-4)
    model.update.delta[2].bias.sum().backward()
    opt.step()
    training = {"step": 12, "optimizer": opt.state_dict(), "rng": torch.get_rng_state()}
    path = save_checkpoint(tmp_path / "run" / "ckpt.pt", model, training, meta={"note": "test", "seqs": [1, 2]})
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == FORMAT and raw["variant"] == "droid"
    loaded, ckpt = load_model(path)
    _assert_same_params(loaded, model.state_dict())
    assert ckpt.source == "pvslam" and ckpt.meta == {"note": "test", "seqs": [1, 2]}
    assert ckpt.training["step"] == 12 and torch.equal(ckpt.training["rng"], training["rng"])
    opt2 = torch.optim.AdamW(loaded.update.parameters(), lr=1e-4)
    opt2.load_state_dict(ckpt.training["optimizer"])  # resumable
    state = opt2.state_dict()["state"]
    assert state.keys() == opt.state_dict()["state"].keys() and len(state) > 0
    assert all(int(v["step"]) == 1 for v in state.values())


def test_own_format_checks(tmp_path, pvo_full_state_dict):
    model = RaftGruNet("pvo")
    model.load_state_dict(pvo_full_state_dict)
    path = save_checkpoint(tmp_path / "pvo.pt", model)
    assert load_model(path)[0].variant == "pvo"
    raw = torch.load(path, weights_only=True)
    with pytest.raises(CheckpointError, match="header says variant='droid'.*keys are those of variant='pvo'"):
        load_checkpoint({**raw, "variant": "droid"})
    with pytest.raises(CheckpointError, match="format_version 2 is not supported"):
        load_checkpoint({**raw, "format_version": 2})
    with pytest.raises(CheckpointError, match="unknown checkpoint format 'other'"):
        load_checkpoint({**raw, "format": "other"})
    with pytest.raises(TypeError, match=r"checkpoint\['training'\]\['fn'\]: function is not weights_only-safe"):
        save_checkpoint(tmp_path / "bad.pt", model, training={"fn": lambda: 0})
    assert not (tmp_path / "bad.pt").exists()
