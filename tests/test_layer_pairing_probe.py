"""bench/layer_pairing_probe.py: each mode changes only the garment stage of the repulsion layer."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from smln.data_sampling import make_scene
from smln.geometry import vertex_normals
from smln.model import SMLN, SMLNConfig
from tests.script_loader import load_script


@pytest.fixture(scope="module")
def step():
    """One step of an untrained full model (body stage on) on a skinned two-layer outfit, with its graph."""
    torch.manual_seed(0)
    model = SMLN(SMLNConfig(latent_size=16, body_repulsion=True)).eval()
    scene = make_scene("tshirt_jacket", "female_average", "05_01_walk", edge_length=0.035, max_frames=4)
    topology = model.make_topology(scene.cloth)
    b = scene.body.vertices
    normals = vertex_normals(b[2], scene.body.faces)
    graph = topology.build(scene.skinned[0], scene.skinned[1], b[1], b[2], body_normals_next=normals)
    return model, topology, graph


def _push(model, topology, graph) -> tuple[torch.Tensor, torch.Tensor]:
    with torch.no_grad():
        _, a, extras = model(graph, topology)
    return a, extras["body_repulsion"]["a"]


def test_modes_change_only_the_garment_stage(step):
    bench = load_script("bench/layer_pairing_probe.py")
    model, topology, graph = step
    a_vertex, a_body = _push(bench.with_mode(model, "vertex"), topology, graph)
    outer = (topology.layer_index == 1).numpy()
    assert float((a_vertex - a_body)[~outer].abs().max()) == 0.0  # the garment stage pushes outer vertices only
    # off: the body stage alone
    a_off, a_body_off = _push(bench.with_mode(model, "off"), topology, graph)
    torch.testing.assert_close(a_off, a_body_off)
    torch.testing.assert_close(a_body_off, a_body)
    # the readings push the outer layer, each its own way, and never the inner one beyond the body stage
    pushes = {}
    for mode in ("surface", "deeper", "deeper_body_guard"):
        a, a_b = _push(bench.with_mode(model, mode), topology, graph)
        torch.testing.assert_close(a_b, a_body)
        assert float((a - a_b)[~outer].abs().max()) == 0.0
        pushes[mode] = a - a_b
    assert model.config.repulsion_pairing == "vertex"  # the modes work on copies
    assert not torch.equal(pushes["surface"], a_vertex - a_body)
    # the body guard leaves no garment-stage push toward the body on a vertex with a body edge
    q, f = graph.body_receivers, graph.body_features
    along = (pushes["deeper_body_guard"][q] * f[:, 9:12]).sum(-1)
    assert float(along.min()) >= -1e-7
    assert float((pushes["deeper"][q] * f[:, 9:12]).sum(-1).min()) < 0.0  # ... which the unguarded one has
    with pytest.raises(ValueError, match="mode"):
        bench.with_mode(model, "sideways")
    assert np.isfinite(a_vertex.numpy()).all()
