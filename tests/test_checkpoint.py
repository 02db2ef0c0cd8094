"""Checkpoints: bit-exact round trip; missing, tampered, pickled and mismatched files are refused."""

import json
import pickle

import pytest
import torch
from safetensors.torch import save_file

from smln.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from smln.model import SMLN, SMLNConfig

CFG = dict(latent_size=16, schedule=((0, 1), (1, 1), (0, 1)))


def trained_like_model() -> SMLN:
    torch.manual_seed(0)
    m = SMLN(SMLNConfig(**CFG)).train()
    m.node_norm(torch.randn(50, 24))  # non-trivial normaliser statistics
    return m


def test_round_trip_bit_exact(tmp_path):
    m = trained_like_model()
    card_path = save_checkpoint(tmp_path / "run1", m, card={"variant": "full", "training": {"steps": 3}})
    assert card_path.name == "run1.json" and (tmp_path / "run1.safetensors").is_file()
    m2, card = load_checkpoint(tmp_path / "run1")
    assert card["variant"] == "full" and card["training"] == {"steps": 3}
    assert card["config"]["latent_size"] == 16
    s1, s2 = m.state_dict(), m2.state_dict()
    assert set(s1) == set(s2)
    for k in s1:
        assert s1[k].dtype == s2[k].dtype and torch.equal(s1[k], s2[k]), k
    assert m2.config == m.config and not m2.training
    # also loadable by either file name, and as a directory
    load_checkpoint(tmp_path / "run1.safetensors")
    save_checkpoint(tmp_path / "dir" / "", m)
    load_checkpoint(tmp_path / "dir")


def test_missing_files(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "nothing")
    save_checkpoint(tmp_path / "a", trained_like_model())
    (tmp_path / "a.safetensors").unlink()
    with pytest.raises(CheckpointError, match="tensors not found"):
        load_checkpoint(tmp_path / "a")


def test_tampered_weights_rejected(tmp_path):
    save_checkpoint(tmp_path / "a", trained_like_model())
    p = tmp_path / "a.safetensors"
    data = bytearray(p.read_bytes())
    data[-5] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="sha256"):
        load_checkpoint(tmp_path / "a")


def test_pickle_renamed_rejected(tmp_path):
    save_checkpoint(tmp_path / "a", trained_like_model())
    p = tmp_path / "a.safetensors"
    p.write_bytes(pickle.dumps({"w": [1, 2, 3]}))
    with pytest.raises(CheckpointError, match="pickle"):
        load_checkpoint(tmp_path / "a")
    torch.save({"w": torch.zeros(2)}, p)  # torch's zip format
    with pytest.raises(CheckpointError, match="zip"):
        load_checkpoint(tmp_path / "a")


def test_shape_mismatch_rejected(tmp_path):
    m = trained_like_model()
    save_checkpoint(tmp_path / "a", m)
    card_path = tmp_path / "a.json"
    card = json.loads(card_path.read_text())
    card["config"]["latent_size"] = 32  # the card now disagrees with the tensors
    card_path.write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match="config needs"):
        load_checkpoint(tmp_path / "a")


def test_bad_card_and_nan_rejected(tmp_path):
    m = trained_like_model()
    save_checkpoint(tmp_path / "a", m)
    card_path = tmp_path / "a.json"
    card = json.loads(card_path.read_text())
    card_path.write_text(json.dumps({**card, "version": 99}))
    with pytest.raises(CheckpointError, match="version"):
        load_checkpoint(tmp_path / "a")
    card_path.write_text("{not json")
    with pytest.raises(CheckpointError, match="JSON"):
        load_checkpoint(tmp_path / "a")
    # NaN weights with a consistent sha256 are still refused
    state = {k: v.clone() for k, v in m.state_dict().items()}
    state["decoder.0.weight"][0, 0] = float("nan")
    save_file(state, str(tmp_path / "a.safetensors"))
    import hashlib

    card["sha256"] = hashlib.sha256((tmp_path / "a.safetensors").read_bytes()).hexdigest()
    card_path.write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match="NaN"):
        load_checkpoint(tmp_path / "a")


def test_card_without_body_normal_field_loads_the_legacy_layout(tmp_path):
    """Cards written before ``body_normal_features`` existed ran 9-column body edges: they load as such (not with
    the new default), and a card that says True needs the 13-column body encoder."""
    torch.manual_seed(0)
    legacy = SMLN(SMLNConfig(**CFG, body_normal_features=False))
    card_path = save_checkpoint(tmp_path / "old", legacy)
    card = json.loads(card_path.read_text())
    del card["config"]["body_normal_features"]
    card_path.write_text(json.dumps(card))
    m, _ = load_checkpoint(tmp_path / "old")
    assert m.config.body_normal_features is False and m.body_encoder[0].in_features == 9
    card["config"]["body_normal_features"] = True
    card_path.write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match="body_encoder"):
        load_checkpoint(tmp_path / "old")
