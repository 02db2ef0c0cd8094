"""scripts/publish_checkpoints.py: a run's checkpoint copied bit-exact to the destination with its cards."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from smln.checkpoint import load_checkpoint, save_checkpoint
from smln.model import SMLN, SMLNConfig
from tests.script_loader import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "publish_checkpoints.py"
publish_checkpoints = load_script("scripts/publish_checkpoints.py")


def test_publish_to_an_experimental_folder(tmp_path):
    torch.manual_seed(0)
    model = SMLN(SMLNConfig(latent_size=16, schedule=((0, 1), (1, 1), (0, 1))))
    run = tmp_path / "runs" / "x_full"
    save_checkpoint(run / "best", model, card={"variant": "full", "training": {"steps": 7, "hardware": "test"}})
    results = [{"method": "full", "outfit": o, "motion": "clip", "split": "train",
                "metrics": {"num_frames": n, "l_coll": lc, "h_coll": 1.0, "bend": 0.1, "collision_loss": 0.0,
                            "strain_mean": 0.05, "ms_model": 30.0, "strain_max_max": 2.0, "fallback_frames": fb}}
               for o, n, lc, fb in (("a", 100, 1.0, 2), ("b", 300, 3.0, 1))]
    dest = tmp_path / "checkpoints" / "experimental" / "set"
    out = publish_checkpoints.publish(run, "full", "best", dest, results)
    assert out == dest / "full"
    loaded, card = load_checkpoint(out)
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    ev = json.loads((out / "card.json").read_text())["evaluation"]
    assert ev["l_coll"] == 2.5  # frame-weighted: (100 * 1 + 300 * 3) / 400
    assert ev["fallback_frames"] == 3 and ev["frames"] == 400
    readme = (out / "README.md").read_text()
    assert f'load_checkpoint("{out.as_posix()}")' in readme  # the folder it was published to, not checkpoints/full
    assert card["training"]["steps"] == 7


def test_publish_a_snapshot_by_its_name(tmp_path):
    torch.manual_seed(1)
    model = SMLN(SMLNConfig(latent_size=16, schedule=((0, 1), (1, 1), (0, 1))))
    run = tmp_path / "runs" / "x_baseline"
    save_checkpoint(run / "snapshots" / "step_0000005", model,
                    card={"variant": "baseline", "training": {"steps": 5, "hardware": "test"}})
    out = publish_checkpoints.publish(run, "baseline", "snapshots/step_0000005", tmp_path / "dest", None)
    loaded, card = load_checkpoint(out)
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    assert card["training"]["steps"] == 5 and "baseline" in (out / "README.md").read_text()


def test_the_cards_name_the_body_stage_and_whether_it_was_frozen(tmp_path):
    torch.manual_seed(2)
    model = SMLN(SMLNConfig(latent_size=16, schedule=((0, 1), (1, 1), (0, 1)), body_repulsion=True))
    with torch.no_grad():  # a stage whose push depends on its input, as training leaves it
        model.body_repulsion.mlp[-1].weight.normal_(0.0, 0.1)
    run = tmp_path / "runs" / "x_full"
    save_checkpoint(run / "trained", model, card={"variant": "full", "training": {"steps": 3, "hardware": "test"}})
    out = publish_checkpoints.publish(run, "full", "trained", tmp_path / "dest0", None)
    readme = (out / "README.md").read_text()
    assert "body stage" in readme and "not trained" not in readme  # a stage whose push depends on its input
    model.body_repulsion.init_as_projection(0.75)  # a constant push, as --freeze-body-stage keeps it
    save_checkpoint(run / "last", model, card={"variant": "full", "training": {"steps": 3, "hardware": "test"}})
    out = publish_checkpoints.publish(run, "full", "last", tmp_path / "dest", None)
    readme = (out / "README.md").read_text()
    description = json.loads((out / "card.json").read_text())["description"]
    for text in (readme, description):
        assert "body stage" in text and "not trained" in text and "0.75 of the way" in text
    # a model without the stage says nothing of one
    plain = SMLN(SMLNConfig(latent_size=16, schedule=((0, 1), (1, 1), (0, 1))))
    save_checkpoint(run / "best", plain, card={"variant": "full", "training": {"steps": 3, "hardware": "test"}})
    out = publish_checkpoints.publish(run, "full", "best", tmp_path / "dest2", None)
    assert "body stage" not in (out / "README.md").read_text()


def test_republishing_names_the_hand_written_sections_it_drops(tmp_path, capsys):
    torch.manual_seed(3)
    model = SMLN(SMLNConfig(latent_size=16, schedule=((0, 1), (1, 1), (0, 1))))
    run = tmp_path / "runs" / "x_baseline"
    save_checkpoint(run / "last", model, card={"variant": "baseline", "training": {"steps": 5, "hardware": "test"}})
    out = publish_checkpoints.publish(run, "baseline", "last", tmp_path / "dest", None)
    assert capsys.readouterr().err == ""  # a first card: nothing to drop
    readme = out / "README.md"
    readme.write_text(readme.read_text() + "\n## Lineage and budget\n\nwritten by hand\n")
    publish_checkpoints.publish(run, "baseline", "last", tmp_path / "dest", None)
    err = capsys.readouterr().err
    assert "## Lineage and budget" in err and str(readme) in err
    assert "written by hand" not in readme.read_text()  # the card is the generated one again
    publish_checkpoints.publish(run, "baseline", "last", tmp_path / "dest", None)
    assert capsys.readouterr().err == ""  # generated sections alone are not reported
