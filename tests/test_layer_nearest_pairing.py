"""The repulsion layer's garment stage read against the inner vertex nearest at t+1
(``SMLNConfig.repulsion_pairing = "nearest"``, :func:`smln.model.smln.nearest_layer_pairs`), on analytic layers."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from smln.model import SMLN, SMLNConfig
from smln.model.smln import REPULSION_PAIRINGS, nearest_layer_pairs
from tests.test_repulsion_pairing import grid


def _two_layers(n_inner: int, n_outer: int) -> SimpleNamespace:
    """A stand-in topology with the two layer slices nearest_layer_pairs reads."""
    return SimpleNamespace(layer_slices=[slice(0, n_inner), slice(n_inner, n_inner + n_outer)])


def test_pairs_are_the_brute_force_nearest_inner_vertex_at_the_prediction() -> None:
    gen = torch.Generator().manual_seed(3)
    n_inner, n_outer = 60, 25
    x_k = torch.rand(n_inner + n_outer, 3, generator=gen) * 0.1
    outer = torch.arange(n_inner, n_inner + n_outer)[::2]  # the stage's outer vertices: a subset
    pairs = nearest_layer_pairs(_two_layers(n_inner, n_outer), x_k, outer, 0)
    expected = torch.cdist(x_k[outer], x_k[:n_inner]).argmin(dim=1)
    assert pairs.shape == (2, len(outer)) and pairs.dtype == torch.long
    assert torch.equal(pairs[0], outer)
    assert torch.equal(pairs[1], expected)


def test_rows_that_are_not_finite_are_left_out() -> None:
    x_k = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.1, 0.0, 0.0],  # inner 0, 1, 2
                        [0.95, 0.0, 0.0], [0.0, 0.1, 0.0], [0.5, 0.5, 0.5]])  # outer 3, 4, 5
    x_k[1] = float("nan")  # an inner vertex with a NaN prediction is nobody's partner
    x_k[5, 2] = float("inf")  # an outer one is not paired
    pairs = nearest_layer_pairs(_two_layers(3, 3), x_k, torch.tensor([3, 4, 5]), 0)
    assert pairs.tolist() == [[3, 4], [2, 0]]
    x_k[:3] = float("nan")
    assert nearest_layer_pairs(_two_layers(3, 3), x_k, torch.tensor([3, 4]), 0).shape == (2, 0)


def _valley_cascade(pairing: str) -> tuple[torch.Tensor, int]:
    """The layer stage on a V-shaped valley z = |x| (inner layer, 25 vertices at 2 cm) and one outer vertex paired
    at step t with the left slope's vertex (-2, 0, 2) cm, predicted 2 mm below the right slope's (2, 0, 2) cm."""
    v, f = grid(height=np.abs)
    left = int(np.flatnonzero(np.all(np.isclose(v, [-0.02, 0.0, 0.02]), axis=1))[0])
    x = torch.as_tensor(np.concatenate([v, [[0.02, 0.0, 0.018]]]), dtype=torch.float32)
    outer = len(v)
    topology = SimpleNamespace(num_layers=2, layer_index=torch.tensor([0] * len(v) + [1]), faces=torch.as_tensor(f),
                               layer_slices=[slice(0, len(v)), slice(len(v), len(v) + 1)])
    graph = SimpleNamespace(repulsion_pairs=torch.tensor([[outer], [left]]), x_cur=x)
    model = SMLN(SMLNConfig(repulsion_pairing=pairing))
    model.repulsion.init_as_projection(1.0)  # a = (threshold - E_r) n for every pair it processes
    model.requires_grad_(False)
    a, _ = model._cascade_repulsion(topology, graph, x, torch.ones(len(x), 1))
    return a, outer


def test_nearest_pushes_the_vertex_its_step_t_partner_reads_far_in_front() -> None:
    # against the left slope's vertex (normal (1, 0, 1)/sqrt 2) the vertex is 2.7 cm in front: no push
    a_vertex, outer = _valley_cascade("vertex")
    assert float(a_vertex.abs().max()) == 0.0
    # against its nearest vertex at t+1, the right slope's (normal (-1, 0, 1)/sqrt 2), it is 1.41 mm behind
    a, outer = _valley_cascade("nearest")
    normal = torch.tensor([-1.0, 0.0, 1.0]) / 2**0.5
    e_r = -0.002 / 2**0.5
    torch.testing.assert_close(a[outer], (0.005 - e_r) * normal, rtol=1e-4, atol=1e-7)
    assert float(a[:outer].abs().max()) == 0.0  # the inner layer is not pushed


def test_config_accepts_the_pairing() -> None:
    assert "nearest" in REPULSION_PAIRINGS
    assert SMLNConfig(repulsion_pairing="nearest").repulsion_pairing == "nearest"
    with pytest.raises(ValueError, match="repulsion_pairing"):
        SMLNConfig(repulsion_pairing="closest")



def test_the_push_of_a_re_paired_vertex_carries_gradient_to_the_layer_mlp() -> None:
    v, f = grid(height=np.abs)
    left = int(np.flatnonzero(np.all(np.isclose(v, [-0.02, 0.0, 0.02]), axis=1))[0])
    x = torch.as_tensor(np.concatenate([v, [[0.02, 0.0, 0.018]]]), dtype=torch.float32)
    topology = SimpleNamespace(num_layers=2, layer_index=torch.tensor([0] * len(v) + [1]), faces=torch.as_tensor(f),
                               layer_slices=[slice(0, len(v)), slice(len(v), len(v) + 1)])
    graph = SimpleNamespace(repulsion_pairs=torch.tensor([[len(v)], [left]]), x_cur=x)
    model = SMLN(SMLNConfig(repulsion_pairing="nearest"))
    a, _ = model._cascade_repulsion(topology, graph, x, torch.ones(len(x), 1))
    a[len(v)].norm().backward()
    grads = [p.grad for p in model.repulsion.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(float(g.abs().max()) > 0 for g in grads)


def test_training_with_both_nearest_readings_stays_finite_and_saves_its_reading(tmp_path) -> None:
    """A few training steps on a real two-layer training outfit with the layer and body stages read nearest at
    t+1: the weights stay finite and the saved card keeps the readings."""
    import json

    from smln.checkpoint import load_checkpoint
    from smln.data_sampling import outfit_names
    from smln.train import train

    outfit = next(o for o in outfit_names("train") if "jacket" in o)
    cfg = {"model": {"latent_size": 16, "body_normal_features": True, "body_repulsion": True,
                     "repulsion_pairing": "nearest", "body_pairing": "nearest"}}
    (tmp_path / "cfg.json").write_text(json.dumps(cfg))
    trainer = train(["--out", str(tmp_path / "run"), "--max-steps", "4", "--outfits", outfit, "--config",
                     str(tmp_path / "cfg.json"), "--motions", "02_01_walk", "--shapes", "female_average",
                     "--save-every", "4", "--validate-every", "100000", "--rollout-max", "2", "--threads", "1"])
    assert trainer.step >= 4
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())
    saved, _ = load_checkpoint(tmp_path / "run" / "last")
    assert (saved.config.repulsion_pairing, saved.config.body_pairing) == ("nearest", "nearest")
