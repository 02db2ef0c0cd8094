"""Training: a few real steps run, resume is bit-for-bit, DDP keeps ranks identical."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from smln.geometry import vertex_normals
from smln.train import Trainer, train

TINY = [
    "--motions", "02_01_walk", "--shapes", "female_average", "--save-every", "4", "--validate-every", "100000",
    "--rollout-max", "3", "--threads", "1",
]


def _outfit() -> str:
    from smln.data_sampling import outfit_names

    return outfit_names("train")[0]


def _params(trainer: Trainer) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in trainer.model.parameters()])


@pytest.mark.slow
def test_training_steps_reduce_nothing_to_nan_and_write_logs(tmp_path):
    trainer = train(["--out", str(tmp_path / "run"), "--max-steps", "6", "--outfits", _outfit(), "--snapshot-every",
                     "2", *TINY])
    assert trainer.step >= 6
    assert torch.isfinite(_params(trainer)).all()
    for name in ("log.csv", "loss.png", "train_state.pt", "config.json"):
        assert (tmp_path / "run" / name).exists(), name
    from smln.checkpoint import load_checkpoint

    model, card = load_checkpoint(tmp_path / "run" / "last")
    assert card["training"]["steps"] == trainer.step
    # checkpoints hold the moving average of the weights
    saved = torch.cat([p.flatten() for p in model.parameters()])
    assert torch.equal(saved, torch.cat([p.detach().flatten() for p in trainer.ema.parameters()]))
    assert not torch.equal(saved, _params(trainer))
    # --snapshot-every 2: the averaged weights kept at least 2 steps apart, each named by its step
    snapshots = sorted((tmp_path / "run" / "snapshots").glob("step_*.json"))
    steps = [int(p.stem.removeprefix("step_")) for p in snapshots]
    assert len(steps) >= 2 and all(b - a >= 2 for a, b in zip(steps, steps[1:], strict=False))
    assert steps[0] >= 2 and steps[-1] <= trainer.step
    for path, step in zip(snapshots, steps, strict=True):
        assert load_checkpoint(path)[1]["training"]["steps"] == step


@pytest.mark.slow
def test_resume_continues_bit_for_bit(tmp_path):
    common = ["--outfits", _outfit(), *TINY]
    straight = train(["--out", str(tmp_path / "a"), "--max-steps", "10", *common])
    first = train(["--out", str(tmp_path / "b"), "--max-steps", "5", *common])
    assert first.step < straight.step
    resumed = train(["--out", str(tmp_path / "b"), "--max-steps", "10", "--resume"])
    assert resumed.step == straight.step
    assert torch.equal(_params(resumed), _params(straight))
    assert torch.equal(torch.cat([p.flatten() for p in resumed.ema.parameters()]),
                       torch.cat([p.flatten() for p in straight.ema.parameters()]))


def test_a_new_run_refuses_an_out_that_holds_a_run_and_leaves_its_files(tmp_path):
    """Without --resume or --force, training into a run's directory would overwrite its state: refused, untouched."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "log.csv").write_text("step,total\n7,1.0\n")
    (out / "train_state.pt").write_bytes(b"the earlier run's state")
    with pytest.raises(FileExistsError, match="--resume.*--force"):
        train(["--out", str(out), "--max-steps", "0", "--outfits", _outfit(), *TINY])
    assert (out / "log.csv").read_text() == "step,total\n7,1.0\n"
    assert (out / "train_state.pt").read_bytes() == b"the earlier run's state"
    assert sorted(p.name for p in out.iterdir()) == ["log.csv", "train_state.pt"]
    # a directory with other files (a config of one's own) is no run: accepted
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    trainer = train(["--out", str(other), "--max-steps", "0", "--outfits", _outfit(), *TINY])
    assert trainer.step == 0 and (other / "notes.txt").read_text() == "mine"
    # --force starts over in it
    forced = train(["--out", str(out), "--max-steps", "0", "--force", "--outfits", _outfit(), *TINY])
    assert forced.step == 0 and (out / "config.json").exists()


@pytest.mark.slow
def test_minutes_is_the_whole_runs_budget_across_resumes(tmp_path):
    """``--minutes`` bounds the run's total wall time: a resumed run that has spent it takes no step."""
    first = train(["--out", str(tmp_path / "b"), "--max-steps", "3", "--outfits", _outfit(), *TINY])
    spent_minutes = first.wall / 60.0
    assert spent_minutes > 0
    spent = train(["--out", str(tmp_path / "b"), "--max-steps", "6", "--resume", "--minutes", str(spent_minutes / 2)])
    assert spent.step == first.step
    more = train(["--out", str(tmp_path / "b"), "--max-steps", "6", "--resume", "--minutes", str(spent_minutes + 30)])
    assert more.step >= 6


@pytest.mark.slow
def test_ddp_two_cpu_processes_keep_identical_parameters(tmp_path):
    script = tmp_path / "ddp_check.py"
    script.write_text(
        "import sys, torch, torch.distributed as dist\n"
        "from smln.train import train\n"
        "t = train(sys.argv[1:])\n"
        "flat = torch.cat([p.detach().flatten() for p in t.model.parameters()])\n"
        "gathered = [torch.zeros_like(flat) for _ in range(dist.get_world_size())]\n"
        "dist.all_gather(gathered, flat)\n"
        "assert all(torch.equal(gathered[0], g) for g in gathered), 'ranks diverged'\n"
        "assert t.step >= 3\n"
        "print('DDP-OK', dist.get_rank(), t.step, flush=True)\n"
        "del t  # its DDP wrapper holds the process group (as cli_main, which keeps no trainer)\n"
        "from smln.train import close_distributed\n"
        "close_distributed()\n"
        "assert not dist.is_initialized()\n"
    )
    env = dict(os.environ, OMP_NUM_THREADS="1")
    # --standalone: torchrun's own rendezvous on a free local port (no port picked here and raced for)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", str(script),
           "--out", str(tmp_path / "ddp"), "--max-steps", "3", "--outfits", _outfit(), *TINY]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=Path(__file__).parents[1])
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    assert res.stdout.count("DDP-OK") == 2


@pytest.mark.slow
def test_episode_window_matches_the_full_clip():
    from smln.data_sampling import SceneCache

    cache = SceneCache(edge_length=0.05)
    full = cache.get(_outfit(), "female_average", "02_01_walk")
    cut = cache.get(_outfit(), "female_average", "02_01_walk", window=(7, 19))
    assert cut.num_frames == 12 and cut.skinned.shape[0] == 12
    torch.testing.assert_close(cut.skinned, full.skinned[7:19])
    torch.testing.assert_close(cut.body.vertices, full.body.vertices[7:19])


@pytest.mark.slow
def test_init_from_checkpoint_keeps_weights_and_step(tmp_path):
    common = ["--outfits", _outfit(), *TINY]
    first = train(["--out", str(tmp_path / "a"), "--max-steps", "4", *common])
    from smln.checkpoint import load_checkpoint

    _, card = load_checkpoint(tmp_path / "a" / "last")
    assert card["training"]["steps"] == first.step
    # zero further steps: the new run holds exactly the checkpoint's weights and step
    second = train(["--out", str(tmp_path / "b"), "--max-steps", str(first.step), "--init-from",
                    str(tmp_path / "a" / "last"), *common])
    assert second.step == first.step
    ema_first = torch.cat([p.detach().flatten() for p in first.ema.parameters()])
    assert torch.equal(_params(second), ema_first)  # the checkpoint holds the moving average
    third = train(["--out", str(tmp_path / "c"), "--max-steps", str(first.step + 2), "--init-from",
                   str(tmp_path / "a" / "last"), *common])
    assert third.step >= first.step + 2
    _, card3 = load_checkpoint(tmp_path / "c" / "last")
    assert card3["initialised_from"]["steps"] == first.step  # the lineage is recorded
    assert not torch.equal(_params(third), ema_first)


@pytest.mark.slow
def test_init_from_a_checkpoint_without_body_normals_widens_it(tmp_path):
    """A run with body-normal edge features initialised from a 9-column checkpoint (all checkpoints before
    session 5) holds the same weights, the body encoder's new input columns at zero, and new normaliser columns."""
    import json

    from smln.checkpoint import load_checkpoint

    common = ["--outfits", _outfit(), *TINY]
    (tmp_path / "legacy.json").write_text(json.dumps({"model": {"body_normal_features": False}}))
    first = train(["--out", str(tmp_path / "a"), "--max-steps", "3", "--config", str(tmp_path / "legacy.json"),
                   *common])
    old, _ = load_checkpoint(tmp_path / "a" / "last")
    assert old.body_encoder[0].in_features == 9
    second = train(["--out", str(tmp_path / "b"), "--max-steps", str(first.step), "--init-from",
                    str(tmp_path / "a" / "last"), *common])
    assert second.model.config.body_normal_features and second.step == first.step
    new_state, old_state = second.model.state_dict(), old.state_dict()
    w = new_state["body_encoder.0.weight"]
    assert w.shape[1] == 13 and torch.equal(w[:, :9], old_state["body_encoder.0.weight"])
    assert torch.count_nonzero(w[:, 9:]) == 0
    for key, value in old_state.items():
        if not key.startswith(("body_encoder.0.weight", "body_norm.total")):
            assert torch.equal(new_state[key], value), key
    mean, std = second.model.body_norm.mean_std()
    assert torch.isfinite(mean).all() and torch.all(std[9:12] > 0.1)  # normal components spread over [-1, 1]
    (tmp_path / "small.json").write_text(json.dumps({"model": {"latent_size": 16}}))
    with pytest.raises(ValueError, match="architecture"):  # anything else that differs is still refused
        train(["--out", str(tmp_path / "c"), "--max-steps", "0", "--init-from", str(tmp_path / "a" / "last"),
               "--config", str(tmp_path / "small.json"), *common])


@pytest.mark.slow
def test_init_from_across_the_repulsion_layer_reading_keeps_the_weights(tmp_path):
    """repulsion_pairing changes how the weights are used, not which there are: a run that reads the layer with the
    surface reading starts from the shipped (vertex-reading) checkpoint's weights and saves its own reading."""
    import json

    from smln.checkpoint import load_checkpoint

    shipped, card = load_checkpoint("checkpoints/full")
    steps = int(card["training"]["steps"])
    (tmp_path / "deeper.json").write_text(json.dumps({"model": {**shipped.config.to_dict(),
                                                                "repulsion_pairing": "deeper"}}))
    trainer = train(["--out", str(tmp_path / "d"), "--max-steps", str(steps), "--init-from", "checkpoints/full",
                     "--config", str(tmp_path / "deeper.json"), "--outfits", _outfit(), *TINY])
    assert trainer.step == steps and trainer.model.config.repulsion_pairing == "deeper"
    for key, value in shipped.state_dict().items():
        assert torch.equal(trainer.model.state_dict()[key], value), key
    saved, _ = load_checkpoint(tmp_path / "d" / "last")
    assert saved.config.repulsion_pairing == "deeper"


@pytest.mark.slow
def test_init_from_the_shipped_checkpoint_into_a_deeper_model_keeps_its_predictions(tmp_path):
    """A run whose model config asks for two hidden layers per MLP and more anchor-level steps, initialised from the
    shipped full checkpoint (one hidden layer), predicts what that checkpoint predicts on a real training state."""
    import json

    from smln.checkpoint import load_checkpoint

    shipped, card = load_checkpoint("checkpoints/full")
    steps = int(card["training"]["steps"])
    # the shipped architecture (whatever stage it has) with the two growable fields grown
    deeper = {**shipped.config.to_dict(), "mlp_hidden_layers": 2,
              "schedule": [[lv, n + (1 if lv > 0 else 0)] for lv, n in shipped.config.schedule]}
    (tmp_path / "deeper.json").write_text(json.dumps({"model": deeper}))
    trainer = train(["--out", str(tmp_path / "g"), "--max-steps", str(steps), "--init-from", "checkpoints/full",
                     "--config", str(tmp_path / "deeper.json"), "--outfits", _outfit(), *TINY])
    assert trainer.step == steps and trainer.model.config.mlp_hidden_layers == 2
    assert sum(p.numel() for p in trainer.model.parameters()) > 1.3 * sum(p.numel() for p in shipped.parameters())
    scene = trainer.cache.get(_outfit(), "female_average", "02_01_walk")
    body_next = scene.body.vertices[6]
    g = scene.topology.build(scene.skinned[4], scene.skinned[5], scene.body.vertices[5], body_next,
                             scene.skinned[6], body_normals_next=vertex_normals(body_next, scene.body.faces))
    shipped.eval()
    trainer.model.eval()
    with torch.no_grad():
        p_old, a_old, _ = shipped(g, scene.topology)
        p_new, a_new, _ = trainer.model(g, scene.topology)
    assert p_old.abs().max() > 1e-5
    torch.testing.assert_close(p_new, p_old, rtol=1e-5, atol=1e-8)
    torch.testing.assert_close(a_new, a_old, rtol=1e-5, atol=1e-8)


def test_ema_update_is_the_moving_average():
    from smln.train import TrainConfig

    cfg = TrainConfig(ema_decay=0.9, model={"latent_size": 8, "schedule": [[0, 1], [1, 1], [0, 1]]})
    trainer = Trainer.__new__(Trainer)  # only the weights, no scenes
    from smln.model import SMLN

    trainer.cfg = cfg
    trainer.model, trainer.ema = SMLN(cfg.model_config()), SMLN(cfg.model_config())
    trainer.cache_tensor_lists()
    before = [p.detach().clone() for p in trainer.ema.parameters()]
    with torch.no_grad():
        for p in trainer.model.parameters():
            p.add_(1.0)
    trainer.update_ema()
    for e, b, p in zip(trainer.ema.parameters(), before, trainer.model.parameters(), strict=True):
        torch.testing.assert_close(e, 0.9 * b + 0.1 * p)


def test_running_mean_of_the_loss_plot_is_exact_at_the_ends():
    """A constant series stays constant (a zero-padded convolution bends its ends towards 0); the ends average
    the samples that exist; the interior is the plain centred mean."""
    import numpy as np

    from smln.train import running_mean

    np.testing.assert_allclose(running_mean(np.full(30, 4.0), 5), np.full(30, 4.0))
    series = np.arange(10, dtype=float)
    out = running_mean(series, 3)
    assert out[0] == pytest.approx((0 + 1) / 2)  # window cut at the start: samples 0, 1
    assert out[-1] == pytest.approx((8 + 9) / 2)
    np.testing.assert_allclose(out[1:-1], series[1:-1])  # a centred mean of a straight line is the line
    np.testing.assert_allclose(running_mean(series, 1), series)


def test_variant_loss_weights():
    """full and no_repulsion_layer train with the repulsion loss (λr of LossWeights.training, or the flag);
    baseline without it; every other weight is the paper's; the friction between layers is off by default and,
    when set, on for every variant."""
    from smln.losses import LossWeights
    from smln.losses.total import TRAINING_REPULSION
    from smln.train import TrainConfig, parse_args

    paper = LossWeights()
    for variant, rep in (("full", TRAINING_REPULSION), ("no_repulsion_layer", TRAINING_REPULSION), ("baseline", 0.0)):
        w = TrainConfig(variant=variant).weights()
        assert w.repulsion == rep
        assert (w.stretch, w.bending, w.gravity, w.friction) == (paper.stretch, paper.bending, paper.gravity,
                                                                  paper.friction)
    cfg, _ = parse_args(["--out", "x", "--variant", "full", "--repulsion-weight", "1000"])
    assert cfg.weights().repulsion == 1e3 == paper.repulsion
    cfg, _ = parse_args(["--out", "x", "--variant", "baseline", "--repulsion-weight", "1000"])
    assert cfg.weights().repulsion == 0.0
    assert w.layer_friction == 0.0  # off unless asked for; then on for every variant (a friction term)
    for variant in ("full", "baseline"):
        cfg, _ = parse_args(["--out", "x", "--variant", variant, "--layer-friction-weight", "1.5"])
        assert cfg.weights().layer_friction == 1.5
        assert not cfg.weights().layer_friction_contact  # the weight alone unless asked for
        cfg, _ = parse_args(["--out", "x", "--variant", variant, "--layer-friction-weight", "1.5",
                             "--layer-friction-normal", "contact"])
        assert cfg.weights().layer_friction_contact
    with pytest.raises(ValueError, match="layer_friction_normal"):
        TrainConfig(variant="full", layer_friction_normal="pressure").weights()
    # the body penalty's clearance: the default 3 mm unless set, for every variant; nonsense values refused
    from smln.losses import COLLISION_EPS

    assert TrainConfig(variant="full").weights().collision_eps == COLLISION_EPS == 3e-3
    for variant in ("full", "baseline"):
        cfg, _ = parse_args(["--out", "x", "--variant", variant, "--collision-eps", "0.0045"])
        assert cfg.weights().collision_eps == 4.5e-3
    for bad in (-1e-3, 0.5):
        with pytest.raises(ValueError, match="collision_eps"):
            TrainConfig(variant="full", collision_eps=bad).weights()
    # and the layers' clearance of the repulsion loss, likewise
    from smln.losses import REPULSION_EPS

    assert TrainConfig(variant="full").weights().repulsion_eps == REPULSION_EPS == 3e-3
    cfg, _ = parse_args(["--out", "x", "--variant", "full", "--repulsion-eps", "0.0045"])
    assert cfg.weights().repulsion_eps == 4.5e-3
    with pytest.raises(ValueError, match="repulsion_eps"):
        TrainConfig(variant="full", repulsion_eps=-1e-3).weights()
    # the layer friction's contact radius follows that clearance unless given (None in the weights)
    assert cfg.weights().layer_friction_radius is None
    cfg, _ = parse_args(["--out", "x", "--variant", "full", "--layer-friction-radius", "0.005"])
    assert cfg.weights().layer_friction_radius == 5e-3
    with pytest.raises(ValueError, match="layer_friction_radius"):
        TrainConfig(variant="full", layer_friction_radius=-1e-3).weights()
    # the stretch weight: the paper's 1 unless set, for every variant (baseline too); nonsense refused
    assert TrainConfig(variant="full").weights().stretch == 1.0
    for variant in ("full", "no_repulsion_layer", "baseline"):
        cfg, _ = parse_args(["--out", "x", "--variant", variant, "--stretch-weight", "2"])
        assert cfg.weights().stretch == 2.0
    for bad in (0.0, -1.0, 1e3):
        with pytest.raises(ValueError, match="stretch_weight"):
            TrainConfig(variant="full", stretch_weight=bad).weights()


def test_learning_rate_schedule_halves_and_restarts():
    from smln.train import TrainConfig

    trainer = Trainer.__new__(Trainer)  # the schedule needs only the config and the step
    trainer.cfg = TrainConfig(lr=1e-4, lr_halving_steps=1000, min_lr=1e-6)
    trainer.step = 0
    assert trainer.learning_rate() == pytest.approx(1e-4)
    assert trainer.learning_rate(2000) == pytest.approx(2.5e-5)
    assert trainer.learning_rate(10_000) == pytest.approx(1e-6)  # floored at min_lr
    trainer.cfg.lr_origin = 5000  # a warm restart at step 5000
    assert trainer.learning_rate(5000) == pytest.approx(1e-4)
    assert trainer.learning_rate(6000) == pytest.approx(5e-5)
    assert trainer.learning_rate(100) == pytest.approx(1e-4)


@pytest.mark.slow
def test_lr_restart_records_the_origin_and_resumes_with_it(tmp_path):
    import json

    common = ["--outfits", _outfit(), *TINY]
    first = train(["--out", str(tmp_path / "a"), "--max-steps", "4", *common])
    second = train(["--out", str(tmp_path / "b"), "--max-steps", str(first.step + 2), "--init-from",
                    str(tmp_path / "a" / "last"), "--lr-restart", "--lr", "3e-5", *common])
    assert second.cfg.lr_origin == first.step
    saved = json.loads((tmp_path / "b" / "config.json").read_text())
    assert saved["lr_origin"] == first.step and saved["lr"] == 3e-5
    assert second.opt.param_groups[0]["lr"] == pytest.approx(second.learning_rate(second.step - 1))
    with pytest.raises(ValueError, match="needs --init-from"):
        train(["--out", str(tmp_path / "c"), "--max-steps", "1", "--lr-restart", *common])


def test_compile_flag_wraps_only_the_trained_copy(tmp_path):
    """--compile: the forward runs through a compiled processor sharing the weights; the saved model keeps its
    own module tree (checkpoint keys unchanged). Nothing is compiled until the first step."""
    from smln.model.compiled import CompiledProcessor
    from smln.train import parse_args

    cfg, _ = parse_args(["--out", str(tmp_path / "run"), "--compile", "--noise-std", "0.001", *TINY])
    assert cfg.compile and cfg.noise_std == 0.001
    trainer = Trainer(cfg, tmp_path / "run")
    assert isinstance(trainer.net.processor, CompiledProcessor) and trainer.net.processor.for_training
    assert trainer.net.processor.inner is trainer.model.processor
    assert not any(k.startswith("processor.inner.") for k in trainer.model.state_dict())
    assert {id(p) for p in trainer.net.parameters()} == {id(p) for p in trainer.model.parameters()}
    default, _ = parse_args(["--out", str(tmp_path / "run2"), *TINY])
    assert default.noise_std == 0.003
    assert not default.compile and not isinstance(Trainer(default, tmp_path / "run2").net.processor,
                                                   CompiledProcessor)


@pytest.mark.slow
def test_validation_rollout_uses_the_configured_skin_guard(tmp_path, monkeypatch):
    """``--validation-skin-guard`` reaches the validation rollout (default: the rollout's plain ``always``)."""
    import smln.rollout
    from smln.train import TrainConfig, parse_args

    common = ["--out", str(tmp_path), "--outfits", _outfit(), *TINY]
    assert parse_args(common)[0].validation_skin_guard == "always"
    cfg, _ = parse_args(common + ["--validation-skin-guard", "symptomatic"])
    trainer = Trainer(cfg, tmp_path)
    calls: list[dict] = []

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return iter(())

    monkeypatch.setattr(smln.rollout, "rollout", spy)
    out = trainer.validate()
    assert len(calls) == 1 and calls[0]["skin_guard"] == "symptomatic" and calls[0]["fallback"] is True
    assert out["val_frames"] == 0.0
    with pytest.raises(SystemExit):
        parse_args(common + ["--validation-skin-guard", "sometimes"])
    with pytest.raises(ValueError, match="validation_skin_guard"):  # the same typo in a config file
        Trainer(TrainConfig(validation_skin_guard="sometimes"), tmp_path / "typo")


def test_normal_input_noise_moves_vertices_along_their_normals_only(tmp_path):
    """``noise_mode="normal"``: each offset is parallel to its vertex normal (Gaussian amount, σ per vertex),
    so edge lengths change to second order only; the isotropic offset changes them to first order. Pinned
    vertices get none in both modes; an unknown mode is refused."""
    from smln.data_sampling import SceneCache
    from smln.geometry import unique_edges, vertex_normals
    from smln.train import TrainConfig

    tiny = {"latent_size": 8, "schedule": [[0, 1], [1, 1], [0, 1]]}
    scene = SceneCache(edge_length=0.05).get("leggings_skirt", "female_average", "02_01_walk")  # pinned waistbands
    x = scene.skinned[3]
    normals = vertex_normals(x, scene.cloth.faces)
    edges = unique_edges(scene.cloth.faces)
    sigma = 0.003

    def edge_change(eps: torch.Tensor) -> torch.Tensor:
        d0 = (x[edges[:, 0]] - x[edges[:, 1]]).norm(dim=-1)
        d1 = (x[edges[:, 0]] + eps[edges[:, 0]] - x[edges[:, 1]] - eps[edges[:, 1]]).norm(dim=-1)
        return (d1 - d0).abs()

    along = Trainer(TrainConfig(noise_std=sigma, noise_mode="normal", model=tiny), tmp_path / "n").input_noise(scene, x)
    iso = Trainer(TrainConfig(noise_std=sigma, model=tiny), tmp_path / "i").input_noise(scene, x)
    free = ~scene.cloth.pinned
    assert scene.cloth.pinned.sum() > 10
    assert (along[scene.cloth.pinned] == 0).all() and (iso[scene.cloth.pinned] == 0).all()
    tangential = along[free] - (along[free] * normals[free]).sum(-1, keepdim=True) * normals[free]
    assert tangential.norm(dim=-1).max() < 1e-7
    amount = (along[free] * normals[free]).sum(-1)
    assert abs(float(amount.std()) - sigma) < 0.1 * sigma and abs(float(amount.mean())) < 0.1 * sigma
    assert 0.8 * sigma * 3**0.5 < float(iso[free].norm(dim=-1).pow(2).mean().sqrt()) < 1.2 * sigma * 3**0.5
    # the same σ: the isotropic offset changes edge lengths several times more (first order, ~√2·σ per edge)
    assert float(edge_change(along).median()) * 3 < float(edge_change(iso).median())
    with pytest.raises(ValueError, match="noise_mode"):
        Trainer(TrainConfig(noise_mode="sideways", model=tiny), tmp_path / "x")


def test_mixed_input_noise_adds_a_normal_offset_to_the_isotropic_one(tmp_path):
    """``noise_normal_std``: the normal-only offset on its own is the ``normal`` mode's offset (same draws);
    added to isotropic noise of σ, the normal component has σ_total = sqrt(σ² + σn²) and the tangential part
    stays the isotropic σ per tangent direction. Negative σ is refused."""
    from smln.data_sampling import SceneCache
    from smln.geometry import vertex_normals
    from smln.train import TrainConfig, parse_args

    tiny = {"latent_size": 8, "schedule": [[0, 1], [1, 1], [0, 1]]}
    scene = SceneCache(edge_length=0.05).get("tshirt_jacket", "female_average", "02_01_walk")
    x = scene.skinned[3]
    normals = vertex_normals(x, scene.cloth.faces)
    only_normal = Trainer(TrainConfig(noise_std=0.0, noise_normal_std=0.002, model=tiny), tmp_path / "a")
    normal_mode = Trainer(TrainConfig(noise_std=0.002, noise_mode="normal", model=tiny), tmp_path / "b")
    assert torch.equal(only_normal.input_noise(scene, x), normal_mode.input_noise(scene, x))
    sigma, sigma_n = 0.0015, 0.0025
    mixed = Trainer(TrainConfig(noise_std=sigma, noise_normal_std=sigma_n, model=tiny), tmp_path / "c")
    eps = mixed.input_noise(scene, x)
    free = ~scene.cloth.pinned
    along = (eps[free] * normals[free]).sum(-1)
    tangential = eps[free] - along[:, None] * normals[free]
    expected = (sigma**2 + sigma_n**2) ** 0.5
    assert abs(float(along.std()) - expected) < 0.1 * expected
    rms_per_direction = float(tangential.pow(2).sum(-1).mean().div(2).sqrt())
    assert abs(rms_per_direction - sigma) < 0.1 * sigma
    assert (eps[scene.cloth.pinned] == 0).all()
    with pytest.raises(ValueError, match="σ must be >= 0"):
        Trainer(TrainConfig(noise_normal_std=-0.001, model=tiny), tmp_path / "d")
    cfg, _ = parse_args(["--out", str(tmp_path / "run"), "--noise-normal-std", "0.0025"])
    assert cfg.noise_normal_std == 0.0025


def _sampler(start_sampling: str, speed_mix: float = 0.5):
    from smln.train import EpisodeSampler, TrainConfig

    cfg = TrainConfig(start_sampling=start_sampling, speed_mix=speed_mix, motions=["02_01_walk"],
                      shapes=["female_average"])
    return EpisodeSampler(cfg, seed=0)


def test_speed_start_probabilities_follow_the_window_speed_analytically():
    # a 3-vertex "body": still for frames 0..9, then moving 1 cm per frame along x (frames 10..19)
    t = torch.arange(20, dtype=torch.float32)
    x = torch.clamp(t - 9.0, min=0.0) * 0.01
    body = torch.zeros(20, 3, 3)
    body[:, :, 0] = x[:, None]
    sampler = _sampler("speed", speed_mix=1.0)
    p = sampler.start_probabilities(("s", "m"), body, length=2, last_start=15)
    assert p.shape == (15,) and abs(p.sum() - 1.0) < 1e-12
    # start s uses body frames s..s+2; speed(t) = 1 cm for t >= 10, else 0. Window means: 0 for s <= 7,
    # 1/3 cm (s = 8), 2/3 cm (s = 9), 1 cm (s >= 10)
    window = np.array([0.0] * 7 + [1 / 3, 2 / 3] + [1.0] * 6)
    np.testing.assert_allclose(p, window / window.sum(), rtol=1e-6)
    # the mixture: half of it uniform
    half = _sampler("speed", speed_mix=0.5).start_probabilities(("s", "m"), body, 2, 15)
    np.testing.assert_allclose(half, 0.5 * window / window.sum() + 0.5 / 15, rtol=1e-6)
    # a still clip: uniform
    still = sampler.start_probabilities(("s2", "m"), torch.zeros(20, 3, 3), 2, 15)
    np.testing.assert_allclose(still, np.full(15, 1 / 15))


def test_speed_start_sampling_draws_fast_phases_more_often_on_a_real_clip():
    from smln.data_sampling import SceneCache

    cache = SceneCache(edge_length=0.05)
    seq = cache.body("female_average", "02_01_walk")
    b = seq.vertices
    speed = np.r_[0.0, (b[1:] - b[:-1]).norm(dim=-1).mean(dim=-1).numpy()]
    starts = {}
    for mode in ("uniform", "speed"):
        sampler = _sampler(mode, speed_mix=1.0)
        for _ in range(20):  # draw() itself runs in both modes
            _, first, length = sampler.draw(0, cache)  # step 0: rollout length rollout_start (2)
            assert first == 1 and length >= 1
        draws = []
        sampler = _sampler(mode, speed_mix=1.0)
        last = seq.num_frames - 2 - 2
        for _ in range(2000):  # the start draw alone (the same generator calls as draw's, without skinning)
            if mode == "speed":
                p = sampler.start_probabilities(("female_average", "02_01_walk"), b, 2, last)
                draws.append(1 + int(sampler.rng.choice(last, p=p)))
            else:
                draws.append(int(sampler.rng.integers(1, last + 1)))
        starts[mode] = np.array(draws)
    mean_speed = {m: speed[s].mean() for m, s in starts.items()}
    assert mean_speed["speed"] > mean_speed["uniform"]


def test_unknown_start_sampling_is_refused(tmp_path):
    from smln.train import TrainConfig

    with pytest.raises(ValueError, match="start_sampling"):
        Trainer(TrainConfig(start_sampling="fast"), tmp_path)
    with pytest.raises(ValueError, match="speed_mix"):
        Trainer(TrainConfig(start_sampling="speed", speed_mix=1.5), tmp_path)


# a full checkpoint without the body stage of the repulsion layer (r25 A, the parent of r27, which was shipped in
# sessions 20-32); the shipped full model has had the stage since session 33
NO_BODY_STAGE = "checkpoints/experimental/body_weight_slow/full"


@pytest.mark.slow
def test_init_from_a_checkpoint_without_a_body_stage_adds_it(tmp_path):
    """A run whose model config adds the body stage of the repulsion layer, initialised from a full checkpoint
    without one: every trained weight is kept (same prediction p on a real training state) and the new stage
    starts at the --body-push-init fraction of a projection onto its threshold."""
    import json

    from smln.checkpoint import load_checkpoint

    parent, card = load_checkpoint(NO_BODY_STAGE)
    steps = int(card["training"]["steps"])
    (tmp_path / "body.json").write_text(json.dumps({"model": {"body_repulsion": True,
                                                              "body_repulsion_threshold": 0.003}}))
    trainer = train(["--out", str(tmp_path / "b"), "--max-steps", str(steps), "--init-from", NO_BODY_STAGE,
                     "--config", str(tmp_path / "body.json"), "--body-push-init", "0.5", "--outfits", _outfit(),
                     *TINY])
    assert trainer.step == steps and trainer.model.config.body_repulsion
    for key, value in parent.state_dict().items():
        assert torch.equal(trainer.model.state_dict()[key], value), key
    scene = trainer.cache.get(_outfit(), "female_average", "02_01_walk")
    body_next = scene.body.vertices[6]
    g = scene.topology.build(scene.skinned[4], scene.skinned[5], scene.body.vertices[5], body_next,
                             scene.skinned[6], body_normals_next=vertex_normals(body_next, scene.body.faces))
    trainer.model.eval()
    with torch.no_grad():
        p_old, _, _ = parent.eval()(g, scene.topology)
        p_new, _, ex = trainer.model(g, scene.topology)
    torch.testing.assert_close(p_new, p_old, rtol=1e-5, atol=1e-8)
    rb = ex["body_repulsion"]
    e = rb["signed_distance"]
    active = (e < 0.003) & (e > -0.02)
    assert active.sum() > 0 and rb["magnitude"].numel() == int(active.sum())
    torch.testing.assert_close(rb["magnitude"], 0.5 * (0.003 - e[active]), rtol=1e-5, atol=1e-9)


def test_a_frozen_body_stage_keeps_its_initial_push_while_the_rest_trains(tmp_path):
    """--freeze-body-stage: after real optimiser steps from a checkpoint without a body stage, the added stage is
    still the 0.5 push it started as (softplus(MLP) = 0.5 for every input), in the trained weights, their moving
    average and the saved checkpoint, while the rest of the network has moved."""
    import json
    import math

    from smln.checkpoint import load_checkpoint

    parent, card = load_checkpoint(NO_BODY_STAGE)
    steps = int(card["training"]["steps"])
    (tmp_path / "body.json").write_text(json.dumps({"model": {"body_repulsion": True}}))
    trainer = train(["--out", str(tmp_path / "f"), "--max-steps", str(steps + 3), "--init-from", NO_BODY_STAGE,
                     "--config", str(tmp_path / "body.json"), "--body-push-init", "0.5", "--freeze-body-stage",
                     "--lr", "1e-3", "--lr-restart", "--outfits", _outfit(), *TINY])
    assert trainer.step >= steps + 3
    saved, _ = load_checkpoint(tmp_path / "f" / "last")
    for model in (trainer.model, trainer.ema, saved):
        last = model.body_repulsion.mlp[-1]
        assert torch.count_nonzero(last.weight) == 0
        assert math.isclose(float(torch.nn.functional.softplus(last.bias.detach())), 0.5, rel_tol=1e-6)
    # the stage's hidden layers are the ones the run drew at construction (seeded), untouched by the steps
    from smln.model.smln import SMLN

    torch.manual_seed(trainer.cfg.seed)
    drawn = SMLN(trainer.cfg.model_config()).body_repulsion.mlp
    for i in (0, 2):
        assert torch.equal(trainer.model.body_repulsion.mlp[i].weight, drawn[i].weight)
        assert torch.equal(saved.body_repulsion.mlp[i].bias, drawn[i].bias)
    moved = [k for k, v in parent.state_dict().items() if not torch.equal(trainer.model.state_dict()[k], v)]
    assert any(k.startswith("processor.") for k in moved)


def test_freezing_the_body_stage_needs_a_model_with_one(tmp_path):
    with pytest.raises(ValueError, match="body_repulsion"):
        train(["--out", str(tmp_path / "x"), "--max-steps", "1", "--freeze-body-stage", "--outfits", _outfit(),
               *TINY])


@pytest.mark.slow
def test_pre_layer_contact_terms_train_the_prediction_before_the_layer(tmp_path):
    """--pre-layer-repulsion / --pre-layer-collision add the contact terms read on x̂: they are logged, they change
    the gradient (same seed, different weights after a few steps), and a variant without the layer refuses them."""
    import csv

    two_layer = _outfit()  # every training outfit has two layers or more
    common = ["--variant", "full", "--max-steps", "4", "--seed", "3", "--outfits", two_layer, "--repulsion-eps", "0.02",
              "--collision-eps", "0.02", *TINY]
    plain = train(["--out", str(tmp_path / "plain"), *common])
    pre = train(["--out", str(tmp_path / "pre"), "--pre-layer-repulsion", "1", "--pre-layer-collision", "1", *common])
    assert not torch.equal(_params(plain), _params(pre))
    with open(tmp_path / "pre" / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows and all(float(r["pre_repulsion"]) >= 0 and float(r["pre_collision"]) >= 0 for r in rows)
    assert any(float(r["pre_repulsion"]) > 0 for r in rows) and any(float(r["pre_collision"]) > 0 for r in rows)
    with pytest.raises(ValueError, match="no layer"):
        train(["--out", str(tmp_path / "norep"), "--variant", "no_repulsion_layer", "--pre-layer-repulsion", "1",
               "--max-steps", "1", "--outfits", two_layer, *TINY])
