"""The repulsion layer's surface reading (``SMLNConfig.repulsion_pairing="deeper"``) and the closest-point query it
uses (:func:`smln.geometry.surface.closest_surface_points`), on analytic surfaces."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from smln.geometry import vertex_normals
from smln.geometry.surface import boundary_edge_keys, closest_surface_points
from smln.model import SMLN, SMLNConfig

CM = 0.01


def grid(n: int = 5, spacing: float = 2 * CM, height=lambda x: np.zeros_like(x)) -> tuple[np.ndarray, np.ndarray]:
    """An n x n heightfield z = height(x) centred on the origin, two triangles per cell (counter-clockwise seen
    from +z, so the normals point up)."""
    c = (np.arange(n) - (n - 1) / 2) * spacing
    xx, yy = np.meshgrid(c, c, indexing="ij")
    v = np.stack([xx.ravel(), yy.ravel(), height(xx.ravel())], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, cc, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, cc], 1), np.stack([a, cc, d], 1)])
    return v, faces.astype(np.int64)


def test_closest_point_on_a_plane_is_the_projection_and_the_edge_is_the_boundary() -> None:
    v, f = grid()
    q = np.array([[0.013, -0.007, 0.02], [0.0, 0.09, 0.01]])  # above the interior; beyond the y = 4 cm edge
    sp = closest_surface_points(q, v, f)
    closest = np.einsum("qk,qkd->qd", sp.bary, v[sp.corners])
    np.testing.assert_allclose(closest[0], [0.013, -0.007, 0.0], atol=1e-9)
    np.testing.assert_allclose(closest[1], [0.0, 0.04, 0.0], atol=1e-9)
    np.testing.assert_allclose(sp.bary.sum(1), 1.0)
    assert sp.on_boundary.tolist() == [False, True]
    # a closed surface has no boundary
    assert len(boundary_edge_keys(np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]), 4)) == 0
    # 5 x 5 grid: 4 sides of 4 edges each
    assert len(boundary_edge_keys(f, len(v))) == 16


def _valley_stage(outer_points: np.ndarray):
    """A V-shaped valley z = |x| (the inner layer, 25 vertices) and outer vertices paired with their nearest
    inner vertex; returns the projection-initialised model, a topology stand-in and the stage's tensors."""
    v, f = grid(height=np.abs)
    x = torch.as_tensor(np.concatenate([v, outer_points]), dtype=torch.float32)
    faces = torch.as_tensor(f)
    outer = torch.arange(len(v), len(x))
    nearest = torch.cdist(x[outer], x[: len(v)]).argmin(1)
    stage = torch.stack([outer, nearest])
    topology = SimpleNamespace(layer_surface=lambda layer: (f, boundary_edge_keys(f, len(x))))
    model = SMLN(SMLNConfig(repulsion_pairing="deeper"))
    model.repulsion.init_as_projection(1.0)  # a = (threshold - E_r) n for every pair it processes
    model.requires_grad_(False)
    return model, topology, x, vertex_normals(x, faces), stage


def test_deeper_pushes_a_vertex_behind_the_triangles_that_its_nearest_vertex_reads_in_front() -> None:
    # (8, 0, 6) mm: 6 mm above the valley vertex's tangent plane z = 0 (threshold 5 mm: the vertex reading does not
    # push), but 1.4 mm below the slope z = x between the valley and the next row
    p = np.array([[0.008, 0.0, 0.006]])
    model, topology, x, n, stage = _valley_stage(p)
    assert int(stage[1, 0]) == 12  # the valley vertex (0, 0, 0), normal +z
    a_vertex, _ = model.repulsion(x, x, n, stage)
    assert float(a_vertex.abs().max()) == 0.0
    a, ex = model._push_deeper(topology, x, x, n, stage, 0)
    push = a[int(stage[0, 0])]
    e_r = float(ex["signed_distance"][0])
    assert -0.002 < e_r < 0.0  # behind the surface (between the slope's 1.41 mm and the interpolated normal's)
    assert float(push.norm()) == pytest.approx(0.005 - e_r, rel=1e-4)
    assert float(push[2]) > 0.0 and float(push[0]) < 0.0  # outward, up the slope's side
    # after the push the surface reading sees the vertex at the threshold (in front)
    x2 = x + a
    sp = closest_surface_points(x2[stage[0]].numpy(), x2.numpy(), topology.layer_surface(0)[0])
    c = np.einsum("qk,qkd->qd", sp.bary, x2.numpy()[sp.corners])
    assert float(((x2[stage[0]].numpy() - c) @ np.array([-1.0, 0.0, 1.0]) / np.sqrt(2))[0]) > 0.003


def test_deeper_keeps_the_vertex_reading_beyond_the_hem() -> None:
    # beyond the y = +4 cm hem and 1 cm below it: the closest surface point is on the hem (no surface reading),
    # so the vertex reading pushes as it would alone
    p = np.array([[0.0, 0.05, -0.01]])
    model, topology, x, n, stage = _valley_stage(p)
    a_vertex, _ = model.repulsion(x, x, n, stage)
    a_deeper, _ = model._push_deeper(topology, x, x, n, stage, 0)
    torch.testing.assert_close(a_deeper, a_vertex, atol=1e-7, rtol=1e-5)
    assert float(a_vertex[stage[0, 0], 2]) > 0.01  # pushed up by about threshold + depth (15 mm)


def test_far_pairs_get_no_push_in_either_reading() -> None:
    p = np.array([[0.008, 0.0, 0.03], [-0.01, 0.01, 0.04]])  # well above the valley
    model, topology, x, n, stage = _valley_stage(p)
    a, ex = model._push_deeper(topology, x, x, n, stage, 0)
    assert float(a.abs().max()) == 0.0 and ex["active_pairs"].shape == (2, 0)


def test_config_rejects_an_unknown_pairing_and_old_cards_read_vertex() -> None:
    with pytest.raises(ValueError, match="repulsion_pairing"):
        SMLNConfig(repulsion_pairing="triangle")
    d = SMLNConfig().to_dict()
    del d["repulsion_pairing"]
    assert SMLNConfig.from_dict(d).repulsion_pairing == "vertex"


def test_the_cli_override_changes_only_models_with_the_layer() -> None:
    from smln.evaluate import apply_repulsion_pairing

    full, ablation = SMLN(SMLNConfig()), SMLN(SMLNConfig(use_repulsion_layer=False))
    assert apply_repulsion_pairing(full, None) is False and full.config.repulsion_pairing == "vertex"
    assert apply_repulsion_pairing(full, "deeper") is True and full.config.repulsion_pairing == "deeper"
    assert apply_repulsion_pairing(full, "deeper") is False  # already so
    assert apply_repulsion_pairing(ablation, "deeper") is False and ablation.config.repulsion_pairing == "vertex"
    with pytest.raises(ValueError, match="pairing"):
        apply_repulsion_pairing(full, "triangle")


def test_a_degenerate_triangle_or_a_nan_query_gives_no_surface_reading() -> None:
    # a collinear (zero-area) triangle closest to the first query, and a NaN query
    v = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.05, 0.0], [0.05, 0.05, 0.0],
                  [0.0, 0.1, 0.0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    sp = closest_surface_points(np.array([[0.01, 0.0, 0.002], [np.nan, 0.0, 0.0], [0.01, 0.06, 0.003]]), v, f)
    assert sp.valid.tolist() == [False, False, True]
    assert np.isfinite(sp.bary).all() and not sp.on_boundary[:2].any()
    from smln.metrics import behind_surface

    assert not behind_surface(np.array([[0.01, 0.0, -0.002]]), v, f).any()


def test_an_invalid_surface_point_leaves_the_vertex_reading(monkeypatch) -> None:
    """A query the closest-point search marks invalid (degenerate triangle, non-finite input) pushes as the vertex
    reading alone would, with finite gradients."""
    import smln.model.smln as smln_model
    from smln.geometry.surface import SurfacePoints

    model, topology, x, n, stage = _valley_stage(np.array([[0.008, 0.0, 0.006], [0.0, 0.05, -0.01]]))
    real = closest_surface_points

    def invalid(points, vertices, faces, boundary=None):
        sp = real(points, vertices, faces, boundary)
        weights = np.tile([1.0, 0.0, 0.0], (len(points), 1))  # what an invalid row holds
        return SurfacePoints(sp.corners, weights, np.zeros_like(sp.on_boundary), np.zeros_like(sp.valid))

    monkeypatch.setattr(smln_model, "closest_surface_points", invalid)
    x_k = x.clone().requires_grad_(True)
    faces = torch.as_tensor(topology.layer_surface(0)[0])
    n_k = vertex_normals(x_k, faces)
    a, _ = model._push_deeper(topology, x, x_k, n_k, stage, 0)
    a_vertex, _ = model.repulsion(x, x_k, n_k, stage)
    torch.testing.assert_close(a, a_vertex)
    a.sum().backward()
    assert torch.isfinite(x_k.grad).all()
