"""Shared fixtures: the golden upstream outputs (``shared/fixtures`` A and B) and networks loaded from them."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from pvslam_plugins.frontends.raft_gru.net import RaftGruNet
from pvslam_plugins.frontends.raft_gru.update import UpdateModule

sys.path.insert(0, str(Path(__file__).parent))  # for _raft_gru_testing


@pytest.fixture(scope="session")
def droid_golden(fixtures_dir: Path) -> dict:
    return torch.load(fixtures_dir / "droid_net_golden.pt", map_location="cpu", weights_only=True)


@pytest.fixture(scope="session")
def pvo_golden(fixtures_dir: Path) -> dict:
    return torch.load(fixtures_dir / "pvo_update_golden.pt", map_location="cpu", weights_only=True)


@pytest.fixture(scope="session")
def droid_net(droid_golden) -> RaftGruNet:
    model = RaftGruNet("droid")
    model.load_state_dict(droid_golden["state_dict"], strict=True)
    return model.eval()


@pytest.fixture(scope="session")
def droid_features(droid_golden, droid_net):
    """``droid_net.features`` of the stored BGR uint8 images (computed once per session)."""
    with torch.no_grad():
        return droid_net.features(droid_golden["images_uint8"])


@pytest.fixture(scope="session")
def pvo_update_state_dict(droid_golden, pvo_golden) -> dict:
    """Full PVO update-module state_dict as the fixture README builds it (shared DROID tensors + PVO-only ones)."""
    sd = {k: droid_golden["state_dict"][v] for k, v in pvo_golden["meta"]["shared_key_map"].items()}
    sd.update(pvo_golden["state_dict_pvo_only"])
    return sd


@pytest.fixture(scope="session")
def pvo_update(pvo_update_state_dict) -> UpdateModule:
    module = UpdateModule("pvo")
    module.load_state_dict(pvo_update_state_dict, strict=True)
    return module.eval()


@pytest.fixture(scope="session")
def pvo_full_state_dict(droid_golden, pvo_update_state_dict) -> dict:
    """A PVO ``DroidNet`` state_dict: DROID's encoders (identical keys and shapes) + the PVO update module."""
    sd = {k: v for k, v in droid_golden["state_dict"].items() if not k.startswith("update.")}
    sd.update({"update." + k: v for k, v in pvo_update_state_dict.items()})
    return sd
