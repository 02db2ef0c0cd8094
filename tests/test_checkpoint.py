"""Checkpoints: bit-exact round trip; missing, tampered, pickled and mismatched files are refused."""

import json
import pickle

import pytest
import torch
from safetensors.torch import save_file

from smln.checkpoint import CheckpointError, average_checkpoints, load_checkpoint, save_checkpoint
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


def test_safetensors_whose_header_length_starts_with_the_pickle_byte_loads(tmp_path):
    """A safetensors file starts with its header length (8 bytes, little-endian); when its low byte is 0x80 the file
    begins like a pickle. It must still load (session 22: a training snapshot was refused as "a pickle")."""
    schedules = (((0, 1), (1, 1), (0, 1)), ((0, 1), (1, 2), (0, 1)), ((0, 2), (1, 1), (0, 1)))

    def saved_head(m: SMLN) -> bytes:
        save_checkpoint(tmp_path / "c", m)
        return (tmp_path / "c.safetensors").read_bytes()[:9]

    # tensor shapes and offsets set the header length: search for a model whose low byte is 0x80
    configs = (SMLNConfig(latent_size=latent, schedule=s) for latent in range(8, 48) for s in schedules)
    m = next(m for m in map(SMLN, configs) if saved_head(m)[0] == 0x80)
    head = (tmp_path / "c.safetensors").read_bytes()[:9]
    assert head[0] == 0x80 and head[8:9] == b"{"
    m2, _ = load_checkpoint(tmp_path / "c")
    assert m2.config == m.config
    for key, value in m.state_dict().items():
        assert torch.equal(m2.state_dict()[key], value), key


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


def _perturbed(model: SMLN, seed: int) -> SMLN:
    """A copy of ``model`` with every parameter moved by N(0, 0.01²) and the buffers unchanged (a fine-tune)."""
    torch.manual_seed(seed)
    other = SMLN(model.config)
    other.load_state_dict(model.state_dict())
    with torch.no_grad():
        for p in other.parameters():
            p.add_(0.01 * torch.randn_like(p))
    return other


def test_average_is_the_weighted_mean_of_parameters_and_keeps_buffers(tmp_path):
    base = trained_like_model()
    a, b = _perturbed(base, 1), _perturbed(base, 2)
    save_checkpoint(tmp_path / "a", a, card={"variant": "full", "training": {"steps": 10, "wall_time_s": 5.0}})
    save_checkpoint(tmp_path / "b", b, card={"variant": "full", "training": {"steps": 12, "wall_time_s": 7.0}})
    card_path = average_checkpoints([tmp_path / "a", tmp_path / "b"], tmp_path / "soup", weights=[3.0, 1.0])
    soup, card = load_checkpoint(card_path)  # a valid checkpoint: sha256, names, shapes
    sa, sb, ss = a.state_dict(), b.state_dict(), soup.state_dict()
    buffers = {name for name, _ in base.named_buffers()}
    for name in ss:
        expected = sa[name] if name in buffers else 0.75 * sa[name] + 0.25 * sb[name]
        assert torch.allclose(ss[name], expected, atol=1e-7), name
    assert card["variant"] == "full" and card["training"]["steps"] == 12 and card["training"]["wall_time_s"] == 12.0
    assert [round(x["weight"], 6) for x in card["averaged_from"]] == [0.75, 0.25]
    # the average of a checkpoint with itself is that checkpoint
    average_checkpoints([tmp_path / "a", tmp_path / "a"], tmp_path / "self")
    same, _ = load_checkpoint(tmp_path / "self")
    for name, value in same.state_dict().items():
        assert torch.equal(value, sa[name]), name


def test_average_refuses_checkpoints_that_do_not_share_a_parent(tmp_path):
    base = trained_like_model()
    save_checkpoint(tmp_path / "a", _perturbed(base, 1), card={"variant": "full"})
    other_stats = _perturbed(base, 2)
    other_stats.node_norm(torch.randn(20, 24))  # other normaliser statistics
    save_checkpoint(tmp_path / "stats", other_stats, card={"variant": "full"})
    save_checkpoint(tmp_path / "variant", _perturbed(base, 3), card={"variant": "baseline"})
    save_checkpoint(tmp_path / "arch", SMLN(SMLNConfig(latent_size=8, schedule=((0, 1),))), card={"variant": "full"})
    with pytest.raises(ValueError, match="buffer 'node_norm"):
        average_checkpoints([tmp_path / "a", tmp_path / "stats"], tmp_path / "out")
    with pytest.raises(ValueError, match="variant"):
        average_checkpoints([tmp_path / "a", tmp_path / "variant"], tmp_path / "out")
    with pytest.raises(ValueError, match="config"):
        average_checkpoints([tmp_path / "a", tmp_path / "arch"], tmp_path / "out")
    with pytest.raises(ValueError, match="at least two"):
        average_checkpoints([tmp_path / "a"], tmp_path / "out")
    with pytest.raises(ValueError, match="weight"):
        average_checkpoints([tmp_path / "a", tmp_path / "a"], tmp_path / "out", weights=[1.0, -1.0])
    assert not (tmp_path / "out.safetensors").exists()


def test_average_cli_refuses_to_overwrite_and_reports_bad_input_in_one_line(tmp_path, capsys):
    from smln.cli import main

    base = trained_like_model()
    save_checkpoint(tmp_path / "a", _perturbed(base, 1), card={"variant": "full"})
    save_checkpoint(tmp_path / "b", _perturbed(base, 2), card={"variant": "full"})
    args = ["average", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "soup")]
    assert main(args) == 0 and load_checkpoint(tmp_path / "soup")
    before = (tmp_path / "soup.safetensors").read_bytes()
    assert main(args) == 2 and "exists" in capsys.readouterr().err
    assert (tmp_path / "soup.safetensors").read_bytes() == before  # nothing the user had is lost
    (tmp_path / "b.safetensors").write_bytes(b"\x80garbage")
    assert main([*args[:3], "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pickle" in err[0]
