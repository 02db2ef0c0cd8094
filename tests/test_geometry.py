"""smln.geometry against trimesh and hand-computed expectations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from smln.geometry import (
    PointTree,
    build_tree,
    close_pairs,
    dihedral_angles,
    face_areas,
    face_normals,
    interior_edges,
    nearest_vertices,
    signed_distance_along_normals,
    unique_edges,
    vertex_normals,
)


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=3)


def _t(a: np.ndarray, dtype=torch.float32) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=dtype)


def test_face_normals_and_areas_match_trimesh(sphere):
    x, f = _t(sphere.vertices), _t(sphere.faces, torch.long)
    np.testing.assert_allclose(face_normals(x, f).numpy(), sphere.face_normals, atol=1e-5)
    np.testing.assert_allclose(face_areas(x, f).numpy(), sphere.area_faces, rtol=1e-4)


def test_vertex_normals_sphere_point_outward(sphere):
    x, f = _t(sphere.vertices), _t(sphere.faces, torch.long)
    n = vertex_normals(x, f)
    np.testing.assert_allclose(torch.linalg.norm(n, dim=-1).numpy(), 1.0, atol=1e-5)
    cos = (n * x / torch.linalg.norm(x, dim=-1, keepdim=True)).sum(-1)
    assert cos.min() > 0.999


def test_vertex_normals_area_weighted():
    # vertex 0 shared by a big face in the xy-plane and a small one in the xz-plane
    x = torch.tensor([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 0.1], [0.1, 0, 0]], dtype=torch.float32)
    f = torch.tensor([[0, 1, 2], [0, 3, 4]])
    n0 = vertex_normals(x, f)[0]
    expected = torch.tensor([0.0, 0.1 * 0.1, 4.0])  # 2*area*normal of each face, summed
    np.testing.assert_allclose(n0.numpy(), (expected / expected.norm()).numpy(), atol=1e-6)


def test_batched_normals_match_unbatched(sphere):
    x, f = _t(sphere.vertices), _t(sphere.faces, torch.long)
    xb = torch.stack([x, 2 * x + 1])
    nb = vertex_normals(xb, f)
    np.testing.assert_allclose(nb[1].numpy(), vertex_normals(xb[1], f).numpy(), atol=1e-6)
    assert face_normals(xb, f).shape == (2, len(sphere.faces), 3)


def test_unique_edges_matches_trimesh(sphere):
    e = unique_edges(_t(sphere.faces, torch.long))
    assert e.dtype == torch.int64
    assert (e[:, 0] < e[:, 1]).all()
    np.testing.assert_array_equal(e.numpy(), np.unique(np.sort(sphere.edges_unique, axis=1), axis=0))


def test_interior_edges_closed_and_open():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    ie = interior_edges(_t(sphere.faces, torch.long))
    assert len(ie.edges) == len(sphere.edges_unique)  # closed: every edge is a hinge
    faces = sphere.faces[ie.face_pairs.numpy()]  # (E, 2, 3)
    for k in range(2):
        assert (faces[:, k] == ie.edges[:, :1].numpy()).any(1).all()
        assert (faces[:, k] == ie.opposite[:, k : k + 1].numpy()).any(1).all()
    # a square of two triangles has one interior edge (0, 2) with opposite 1 and 3
    quad = torch.tensor([[0, 1, 2], [0, 2, 3]])
    ie = interior_edges(quad)
    assert sorted(ie.edges[0].tolist()) == [0, 2]
    assert sorted(ie.opposite[0].tolist()) == [1, 3]


def test_dihedral_angle_of_folded_pair():
    phi = 0.7
    x = torch.tensor([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -math.cos(phi), math.sin(phi)]], dtype=torch.float64)
    ie = interior_edges(torch.tensor([[0, 1, 2], [1, 0, 3]]))
    theta = dihedral_angles(x, ie.edges, ie.opposite)
    assert abs(abs(theta.item()) - phi) < 1e-9
    x[3, 2] = 0.0
    x[3, 1] = -1.0
    assert abs(dihedral_angles(x, ie.edges, ie.opposite).item()) < 1e-9


def test_nearest_and_signed_distance(sphere):
    ref = _t(sphere.vertices)
    normals = vertex_normals(ref, _t(sphere.faces, torch.long))
    query = torch.cat([ref[:10] * 1.01, ref[10:20] * 0.99])
    idx, dist = nearest_vertices(query, ref)
    np.testing.assert_array_equal(idx.numpy(), np.arange(20))
    np.testing.assert_allclose(dist.numpy(), 0.01, atol=1e-5)
    idx2, d = signed_distance_along_normals(query, ref, normals, tree=build_tree(ref))
    assert (d[:10] > 0).all() and (d[10:] < 0).all()
    # numpy input and the differentiable path
    q = query.clone().requires_grad_(True)
    _, d = signed_distance_along_normals(q, ref, normals, idx=idx2)
    d.sum().backward()
    np.testing.assert_allclose(q.grad.numpy(), normals[:20].numpy(), atol=1e-6)
    idx3, _ = nearest_vertices(query.numpy(), tree=build_tree(ref.numpy()))
    assert torch.equal(idx3, idx)


def test_close_pairs_radius_and_k():
    ref = torch.tensor([[0, 0, 0], [0.01, 0, 0], [1, 0, 0]], dtype=torch.float32)
    query = torch.tensor([[0, 0, 0.005], [5, 5, 5]], dtype=torch.float32)
    qi, ri, d = close_pairs(query, ref, radius=0.02, k=2)
    assert qi.tolist() == [0, 0]
    assert ri.tolist() == [0, 1]
    assert d[0] < d[1] < 0.02
    qi, ri, _ = close_pairs(query, ref, radius=0.004, k=2)
    assert len(qi) == 0


def test_vertex_neighbors(sphere):
    from smln.geometry import vertex_neighbors

    f = _t(sphere.faces, torch.long)
    nb = vertex_neighbors(f)
    assert nb.shape == (len(sphere.vertices), 6)  # icosphere valence 5 or 6, padded with self
    for i in [0, 50, 600]:
        assert set(nb[i].tolist()) - {i} == set(sphere.vertex_neighbors[i])


def test_point_tree_matches_brute_force_and_scipy_conventions():
    rng = np.random.default_rng(3)
    ref = rng.uniform(-1, 1, (400, 3)).astype(np.float32)
    q = rng.uniform(-1.2, 1.2, (150, 3)).astype(np.float32)
    d_all = np.linalg.norm(q[:, None, :].astype(np.float64) - ref[None].astype(np.float64), axis=-1)
    tree = PointTree(ref)
    dist, idx = tree.query(q)
    assert idx.dtype == np.int64 and dist.shape == (150,)
    np.testing.assert_allclose(dist, d_all.min(1), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(d_all[np.arange(150), idx], d_all.min(1), rtol=1e-5, atol=1e-6)
    # k nearest within a bound: ascending, missing ones are (inf, n) as in scipy
    dist3, idx3 = tree.query(q, k=3, distance_upper_bound=0.2)
    assert dist3.shape == idx3.shape == (150, 3)
    srt = np.sort(d_all, 1)[:, :3]
    want = np.where(srt < 0.2, srt, np.inf)
    np.testing.assert_allclose(dist3, want, rtol=1e-5, atol=1e-6)
    assert np.all((idx3 == 400) == np.isinf(dist3))
    # more neighbours than points, and an empty tree
    d5, i5 = PointTree(ref[:2]).query(q[:4], k=5)
    assert np.isinf(d5[:, 2:]).all() and (i5[:, 2:] == 2).all() and np.isfinite(d5[:, :2]).all()
    d0, i0 = PointTree(np.zeros((0, 3))).query(q[:4])
    assert np.isinf(d0).all() and (i0 == 0).all()
    with pytest.raises(ValueError, match="points"):
        PointTree(np.zeros((5, 2)))


def test_point_tree_non_finite_input():
    """NaN/inf query rows have no neighbour (inf, n) instead of garbage indices; non-finite points are refused."""
    ref = np.random.default_rng(0).uniform(size=(50, 3))
    q = np.zeros((4, 3), np.float32)
    q[1, 0], q[2, 2] = np.nan, np.inf
    for k in (1, 2):
        dist, idx = PointTree(ref).query(q, k=k)
        assert np.isinf(dist[[1, 2]]).all() and (idx[[1, 2]] == 50).all()
        assert np.isfinite(dist[[0, 3]]).all() and (idx[[0, 3]] < 50).all()
    with pytest.raises(ValueError, match="NaN"):
        PointTree(np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]))
