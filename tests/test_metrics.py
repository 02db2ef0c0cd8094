"""smln.metrics on concentric spheres with known penetrations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from smln.losses import ClothRest
from smln.metrics import FrameMetrics, frame_metrics, sequence_metrics
from tests.test_losses import grid, make_cloth


@pytest.fixture(scope="module")
def body() -> tuple[torch.Tensor, torch.Tensor]:
    s = trimesh.creation.icosphere(subdivisions=4)
    return torch.as_tensor(s.vertices, dtype=torch.float32), torch.as_tensor(s.faces)


@pytest.fixture(scope="module")
def shell() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=3)


def stack(shell: trimesh.Trimesh, radii: list[float]) -> tuple[ClothRest, list[np.ndarray]]:
    """Concentric sphere layers (same mesh) at the given radii, inner -> outer; unit directions per layer."""
    rest = ClothRest.from_cloth(make_cloth([(shell.vertices * r, shell.faces) for r in radii]))
    return rest, [np.asarray(shell.vertices, dtype=np.float32)] * len(radii)


def test_h_coll_inside_and_outside(body, shell):
    b, bf = body
    rest, (u,) = stack(shell, [1.01])
    inside = u[:, 2] > 0.3
    x = np.where(inside[:, None], u * 0.99, u * 1.01)
    m = frame_metrics(x, b, rest, body_faces=bf)
    assert math.isclose(m.values["h_coll"], 100 * inside.mean(), abs_tol=1e-9)
    np.testing.assert_array_equal(m.body_penetration, inside)
    assert not m.layer_penetration.any()
    assert m.values["l_coll"] == 0.0 and m.values["nan"] == 0.0 and m.values["exploded"] == 0.0
    # all 1 cm outside: nothing; a prebuilt tree and normals give the same result
    from smln.geometry import build_tree, vertex_normals

    m2 = frame_metrics(u * 1.01, b, rest, body_normals=vertex_normals(b, bf), body_tree=build_tree(b))
    assert m2.values["h_coll"] == 0.0 and m2.values["collision_loss"] == 0.0


def test_collision_loss_layersnet(body, shell):
    b, bf = body
    rest, (u,) = stack(shell, [1.01])
    deep = u[:, 0] > 0.5
    x = np.where(deep[:, None], u * 0.998, u * 1.01)  # 2 mm inside: v = -2 mm - 1 mm
    m = frame_metrics(x, b, rest, body_faces=bf)
    assert math.isclose(m.values["collision_loss"], 0.003**2, rel_tol=1e-3)


def test_l_coll_outer_pushed_through_inner(body, shell):
    b, bf = body
    rest, (u0, u1) = stack(shell, [1.01, 1.02])
    through = u1[:, 2] > 0.5
    x = np.concatenate([u0 * 1.01, np.where(through[:, None], u1 * 1.0, u1 * 1.02)])
    m = frame_metrics(torch.as_tensor(x), b * 0.9, rest, body_faces=bf)
    assert math.isclose(m.values["l_coll"], 100 * through.mean(), abs_tol=1e-9)
    assert m.values["l_coll_1_0"] == m.values["l_coll"]
    assert m.values["h_coll"] == 0.0
    np.testing.assert_array_equal(m.layer_penetration, np.concatenate([np.zeros(len(u0), bool), through]))


def test_per_pair_l_coll_three_layers(body, shell):
    b, bf = body
    rest, (u, _, _) = stack(shell, [1.01, 1.02, 1.03])
    mid_back = u[:, 2] > 0.5  # layer 1 behind layer 0 there
    out_back = (u[:, 0] > 0.5) & ~mid_back  # layer 2 behind layer 1, in front of layer 0
    x = np.concatenate(
        [u * 1.01, np.where(mid_back[:, None], u * 1.005, u * 1.02), np.where(out_back[:, None], u * 1.016, u * 1.03)]
    )
    m = frame_metrics(x, b * 0.9, rest, body_faces=bf)
    assert math.isclose(m.values["l_coll_1_0"], 100 * mid_back.mean(), abs_tol=1e-9)
    assert math.isclose(m.values["l_coll_2_1"], 100 * out_back.mean(), abs_tol=1e-9)
    # union of inner layers: nearest is layer 1 (4 mm) -> behind it, so the same vertices count
    assert math.isclose(m.values["l_coll"], 100 * out_back.mean(), abs_tol=1e-9)
    np.testing.assert_array_equal(m.layer_penetration, np.concatenate([np.zeros(len(u), bool), mid_back, out_back]))


def test_bend_strain_nan_and_sequence(body):
    b, bf = body
    v, f = grid(4)
    rest = ClothRest.from_cloth(make_cloth([(v, f)]))
    x = torch.as_tensor(v, dtype=torch.float32) + torch.tensor([0.0, 0.0, 3.0])
    m = frame_metrics(x * 1.1, b, rest, body_faces=bf)
    assert m.values["bend"] < 1e-6
    assert math.isclose(m.values["strain_mean"], 0.1, rel_tol=1e-4)
    assert math.isclose(m.values["strain_max"], 0.1, rel_tol=1e-4)
    assert m.values["exploded"] == 1.0  # more than 1 m from the body
    phi = 0.5
    pair = (np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0]]), np.array([[0, 1, 2], [1, 0, 3]]))
    rest2 = ClothRest.from_cloth(make_cloth([pair]))
    x2 = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -math.cos(phi), math.sin(phi)]]) * 0.2 + [0, 0, 1.0]
    m2 = frame_metrics(x2, b, rest2, body_faces=bf)
    assert math.isclose(m2.values["bend"], 1 - math.cos(phi), rel_tol=1e-4)
    bad = x.clone()
    bad[3, 0] = float("nan")
    m3 = frame_metrics(bad, b, rest, body_faces=bf)
    assert m3.values["nan"] == 1.0 and m3.values["exploded"] == 1.0 and math.isnan(m3.values["h_coll"])
    seq = sequence_metrics(
        [m2, m3, FrameMetrics(dict(m2.values), m2.body_penetration, m2.layer_penetration, m2.body_index,
                         m2.body_distance)]
    )
    assert seq["num_frames"] == 3.0
    assert math.isclose(seq["bend"], m2.values["bend"], rel_tol=1e-6)
    assert math.isclose(seq["nan"], 1 / 3) and seq["first_exploded_frame"] == 1.0
    assert seq["strain_max_max"] == m2.values["strain_max"]


def _reference_metrics(x: np.ndarray, b: np.ndarray, bf: np.ndarray, rest: ClothRest) -> dict:
    """Straightforward float64 reference: brute-force nearest vertices, per-face loops for the normals."""
    x = x.astype(np.float64)
    b = b.astype(np.float64)

    def vnormals(v: np.ndarray, faces: np.ndarray, eps_inside: bool) -> np.ndarray:
        acc = np.zeros_like(v)
        for i, j, k in faces:  # area-weighted: the unnormalised cross product of each face
            c = np.cross(v[j] - v[i], v[k] - v[i])
            acc[i] += c
            acc[j] += c
            acc[k] += c
        norm = np.linalg.norm(acc, axis=1, keepdims=True)
        return acc / (np.sqrt(norm**2 + 1e-12) if eps_inside else norm + 1e-12)

    def nearest(q: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dm = np.linalg.norm(q[:, None, :] - ref[None, :, :], axis=-1)
        i = dm.argmin(axis=1)
        return dm[np.arange(len(q)), i], i

    def loss(d: np.ndarray, dist: np.ndarray) -> float:
        v = [min(di - 1e-3, 0.0) for di, si in zip(d, dist, strict=True) if di >= -1e-2 and si < 1e-2]
        v = [vi for vi in v if vi != 0.0]
        return sum(vi * vi for vi in v) / len(v) if v else 0.0

    out: dict = {}
    bdist, bi = nearest(x, b)
    bn = vnormals(b, bf, eps_inside=True)
    d = np.einsum("ij,ij->i", x - b[bi], bn[bi])
    out["body_penetration"] = d < 0
    out["h_coll"] = 100.0 * np.mean(d < 0)
    out["collision_loss"] = loss(d, bdist)
    f = rest.faces.numpy()
    cn = vnormals(x, f, eps_inside=False)
    sl = rest.layer_slices
    layer_pen = np.zeros(len(x), bool)
    for k in range(1, len(sl)):
        xo, xi = x[sl[k]], x[sl[k - 1]]
        _, j = nearest(xo, xi)
        dk = np.einsum("ij,ij->i", xo - xi[j], cn[sl[k - 1]][j])
        layer_pen[sl[k]] = dk < 0
        out[f"l_coll_{k}_{k - 1}"] = 100.0 * np.mean(dk < 0)
    inner = np.arange(sl[-1].start)  # union of the inner layers (contiguous, before the outermost)
    dist, j = nearest(x[sl[-1]], x[inner])
    dl = np.einsum("ij,ij->i", x[sl[-1]] - x[inner][j], cn[inner][j])
    out["l_coll"] = 100.0 * np.mean(dl < 0)
    out["layer_collision_loss"] = loss(dl, dist)
    out["layer_penetration"] = layer_pen
    fn = np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    out["bend"] = np.mean([1.0 - fn[p] @ fn[q] for p, q in rest.hinge_faces.numpy()])
    e = rest.edges.numpy()
    strain = np.abs(np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / rest.rest_length.numpy() - 1.0)
    out["strain_mean"], out["strain_max"] = strain.mean(), strain.max()
    out["body_index"] = bi
    return out


@pytest.mark.parametrize("prebuilt", [False, True])
def test_matches_brute_force_reference_three_layers(prebuilt):
    """The vectorised frame_metrics equals a brute-force float64 computation on a small noisy 3-layer outfit."""
    rng = np.random.default_rng(3)
    bs = trimesh.creation.icosphere(subdivisions=3)  # 4x denser than the cloth: normals of a vertex subset
    b = (bs.vertices * [1.0, 0.8, 1.3] + rng.normal(0, 0.004, bs.vertices.shape)).astype(np.float32)
    bf = np.asarray(bs.faces)
    s = trimesh.creation.icosphere(subdivisions=2)
    shells = [(s.vertices * [1.0, 0.8, 1.3] * r, s.faces) for r in (1.008, 1.016, 1.024)]
    rest = ClothRest.from_cloth(make_cloth(shells))
    x = np.concatenate([v for v, _ in shells])
    x = x + rng.normal(0, 0.005, x.shape)
    x = x.astype(np.float32)
    kw = {"body_faces": torch.as_tensor(bf)}
    if prebuilt:
        from smln.geometry import build_tree, vertex_normals

        kw = {"body_normals": vertex_normals(torch.as_tensor(b), torch.as_tensor(bf)), "body_tree": build_tree(b)}
    m = frame_metrics(x, b, rest, **kw)
    ref = _reference_metrics(x, b, bf, rest)
    # the noise makes collisions of every kind, so the test is not vacuous
    for k in ("h_coll", "l_coll", "l_coll_1_0", "l_coll_2_1", "collision_loss", "layer_collision_loss"):
        assert ref[k] > 0, k
    assert ref["l_coll"] != ref["l_coll_2_1"]  # the union's nearest is sometimes on layer 0
    for k in ("h_coll", "l_coll", "l_coll_1_0", "l_coll_2_1"):
        assert m.values[k] == pytest.approx(ref[k], abs=1e-9), k
    for k in ("collision_loss", "layer_collision_loss", "bend", "strain_mean", "strain_max"):
        assert m.values[k] == pytest.approx(ref[k], rel=1e-4), k
    np.testing.assert_array_equal(m.body_penetration, ref["body_penetration"])
    np.testing.assert_array_equal(m.layer_penetration, ref["layer_penetration"])
    np.testing.assert_array_equal(m.body_index, ref["body_index"])
    assert m.values["nan"] == 0.0 and m.values["exploded"] == 0.0


def _two_layers(inner_v, inner_f, outer_v, outer_f):
    x = np.concatenate([inner_v, outer_v]).astype(np.float32)
    faces = np.concatenate([inner_f, outer_f + len(inner_v)]).astype(np.int64)
    li = np.concatenate([np.zeros(len(inner_v)), np.ones(len(outer_v))]).astype(np.int64)
    return x, faces, li


def test_surface_l_coll_concentric_spheres():
    from smln.metrics import surface_l_coll, surface_layer_penetration

    s = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    assert surface_l_coll(*_two_layers(v, f, 1.05 * v, f)) == 0.0  # outer layer outside everywhere
    assert surface_l_coll(*_two_layers(v, f, 0.95 * v, f)) == 100.0  # outer layer inside everywhere
    # a cap of the outer sphere pushed inside: exactly those vertices
    outer = 1.05 * v
    cap = v[:, 2] > 0.8
    outer[cap] = 0.97 * v[cap]
    x, faces, li = _two_layers(v, f, outer, f)
    mask = surface_layer_penetration(x, faces, li)
    assert not mask[li == 0].any()
    np.testing.assert_array_equal(mask[li == 1], cap)
    assert surface_l_coll(*_two_layers(v, f, v * 1.05, f)[:2], np.zeros(2 * len(v), np.int64)) == 0.0  # 1 layer


def test_surface_l_coll_beyond_a_hem_is_not_a_collision():
    """An inner hemisphere (open at the equator) under a smaller full sphere: the outer vertices of the lower half
    lie beyond the hem (closest point on the boundary) and do not count; the upper half is behind the surface."""
    from smln.metrics import surface_layer_penetration

    s = trimesh.creation.icosphere(subdivisions=3)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    keep = v[f].mean(axis=1)[:, 2] > 0.0
    hemi = trimesh.Trimesh(v, f[keep], process=False)
    hemi.remove_unreferenced_vertices()
    x, faces, li = _two_layers(np.asarray(hemi.vertices), np.asarray(hemi.faces), 0.95 * v, f)
    mask = surface_layer_penetration(x, faces, li)[li == 1]
    z = v[:, 2]
    assert mask[z > 0.2].all()
    assert not mask[z < -0.05].any()


def test_surface_l_coll_ignores_the_nearest_vertex_artefact_on_a_ridge():
    """A coarse roof (45 degree flanks, 3.5 cm edges) and an outer vertex 3 mm outside a flank next to the ridge:
    its nearest inner vertex is on the ridge, whose normal points up, so the vertex test (L-Coll) calls it behind
    the layer; the closest point on the triangles is on the flank, 3 mm below it: no collision."""
    from scipy.spatial import cKDTree

    from smln.geometry import vertex_normals
    from smln.metrics import surface_layer_penetration

    h = 0.035
    xs, ys = np.array([-2, -1, 0, 1, 2]) * h, np.arange(5) * h
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    inner = np.stack([gx.ravel(), gy.ravel(), -np.abs(gx.ravel())], axis=1)
    n_y = len(ys)
    quads = [(i * n_y + j, (i + 1) * n_y + j, (i + 1) * n_y + j + 1, i * n_y + j + 1)
             for i in range(len(xs) - 1) for j in range(n_y - 1)]
    inner_f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    p = np.array([[0.012, 2 * h, -0.012 + 3e-3 * math.sqrt(2)]])  # 3 mm outside the x > 0 flank
    x, faces, li = _two_layers(inner, inner_f, p, np.zeros((0, 3), np.int64))
    # the vertex test: nearest inner vertex and its normal
    normals = vertex_normals(torch.as_tensor(inner, dtype=torch.float32), torch.as_tensor(inner_f)).numpy()
    _, j = cKDTree(inner).query(p[0])
    assert np.dot(p[0] - inner[j], normals[j]) < 0  # L-Coll's test fires
    assert not surface_layer_penetration(x, faces, li)[-1]  # the surface test does not
    p_in = np.array([[0.012, 2 * h, -0.012 - 3e-3 * math.sqrt(2)]])  # 3 mm inside the flank: a real collision
    assert surface_layer_penetration(*_two_layers(inner, inner_f, p_in, np.zeros((0, 3), np.int64)))[-1]


def test_surface_h_coll_closed_body():
    from smln.metrics import surface_h_coll

    s = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.where(np.arange(400) < 100, 0.19, 0.21)  # 100 of 400 points 1 cm inside, the rest 1 cm outside
    assert surface_h_coll(d * r[:, None], v, f) == pytest.approx(25.0)


def test_layer_slip_measures_the_tangential_slide_of_touching_layers():
    """Outer sheet 4 mm above the inner one: sliding it 2 mm along x reads 2 mm; both sheets moving together, or
    the outer one moving along the normal only, read 0; sheets 1 cm apart (not touching) and a single layer read
    NaN."""
    import math

    import torch

    from smln.losses import ClothRest
    from smln.metrics import layer_slip
    from tests.test_losses import grid, make_cloth, two_sheets

    rest, x = two_sheets(0.004)
    slide = x.clone()
    slide[9:, 0] += 0.002
    assert math.isclose(layer_slip(x, slide, rest), 0.002, rel_tol=1e-4)
    assert layer_slip(x, x + torch.tensor([0.01, -0.02, 0.005]), rest) < 1e-7
    lift = x.clone()
    lift[9:, 2] -= 0.001
    assert layer_slip(x, lift, rest) < 1e-7
    _, apart = two_sheets(0.01)
    moved = apart.clone()
    moved[9:, 0] += 0.002
    assert math.isnan(layer_slip(apart, moved, rest))
    v, f = grid(3, size=0.02)
    single = ClothRest.from_cloth(make_cloth([(v, f)]))
    assert math.isnan(layer_slip(torch.as_tensor(v, dtype=torch.float32), torch.as_tensor(v, dtype=torch.float32),
                                 single))
