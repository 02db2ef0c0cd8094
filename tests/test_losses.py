"""smln.losses against closed forms derived by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from smln.cloth import GRAVITY, Cloth, Material
from smln.geometry import vertex_normals
from smln.losses import (
    COLLISION_EPS,
    BodyStep,
    ClothRest,
    LossWeights,
    bending_energy,
    collision_energy,
    friction_energy,
    gravity_energy,
    inertia_energy,
    layer_friction_energy,
    layer_pairs,
    pre_layer_contact_loss,
    repulsion_energy,
    stretch_energy,
    total_loss,
)


def make_cloth(layers: list[tuple[np.ndarray, np.ndarray]], material: Material | None = None) -> Cloth:
    """Concatenate (vertices, faces) layers, inner -> outer, into a Cloth with masses rho * A / 3."""
    material = material or Material()
    verts, faces, lidx, off = [], [], [], 0
    for k, (v, f) in enumerate(layers):
        verts.append(np.asarray(v, dtype=np.float32))
        faces.append(np.asarray(f, dtype=np.int64) + off)
        lidx.append(np.full(len(v), k))
        off += len(v)
    x = torch.as_tensor(np.concatenate(verts))
    f = torch.as_tensor(np.concatenate(faces))
    area = 0.5 * torch.linalg.norm(
        torch.linalg.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]]), dim=-1
    )
    mass = torch.zeros(len(x)).index_add(0, f.reshape(-1), (material.density * area / 3).repeat_interleave(3))
    n = len(x)
    return Cloth(
        rest_vertices=x,
        faces=f,
        layer_index=torch.as_tensor(np.concatenate(lidx)),
        vertex_mass=mass,
        pinned=torch.zeros(n, dtype=torch.bool),
        skin_indices=torch.zeros(n, 1, dtype=torch.long),
        skin_weights=torch.ones(n, 1),
        material=material,
    )


TRI = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32), np.array([[0, 1, 2]]))


def grid(n: int = 4, size: float = 1.0, z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n vertex grid in the plane z, normals +Z."""
    u = np.linspace(0, size, n)
    xx, yy = np.meshgrid(u, u, indexing="ij")
    v = np.stack([xx.ravel(), yy.ravel(), np.full(n * n, z)], 1)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, f


def test_stretch_zero_at_rest_and_rigid_motion():
    s = trimesh.creation.icosphere(subdivisions=2)
    rest = ClothRest.from_cloth(make_cloth([(s.vertices, s.faces)]))
    x = torch.as_tensor(s.vertices, dtype=torch.float32)
    assert stretch_energy(x, rest).item() < 1e-9
    rot = torch.as_tensor(
        trimesh.transformations.rotation_matrix(0.8, [1, 2, 3])[:3, :3], dtype=torch.float32
    )
    assert stretch_energy(x @ rot.T + 0.3, rest).item() < 1e-8


def test_stretch_closed_form_uniform_and_uniaxial():
    m = Material()
    rest = ClothRest.from_cloth(make_cloth([TRI], m))
    x0 = torch.as_tensor(TRI[0])
    area, s = 0.5, 1.1
    g = 0.5 * (s * s - 1.0)
    # uniform: F^T F = s^2 I, G = g I, tr(S^T G) = mu * 2 g^2 + lambda/2 * (2 g)^2
    expected = area * m.thickness * 2.0 * g * g * (m.lame_mu + m.lame_lambda)
    assert math.isclose(stretch_energy(x0 * s, rest).item(), expected, rel_tol=1e-5)
    # uniaxial along x: G = diag(g, 0), tr(S^T G) = mu g^2 + lambda/2 g^2
    x1 = x0 * torch.tensor([s, 1.0, 1.0])
    expected = area * m.thickness * g * g * (m.lame_mu + 0.5 * m.lame_lambda)
    assert math.isclose(stretch_energy(x1, rest).item(), expected, rel_tol=1e-5)


def test_bending_flat_zero_and_folded_pair():
    v, f = grid(4)
    rest = ClothRest.from_cloth(make_cloth([(v, f)]))
    x = torch.as_tensor(v, dtype=torch.float32)
    assert bending_energy(x, rest).item() == 0.0
    assert bending_energy(x * 2 + 1, rest).item() < 1e-12  # scaled, translated, still flat
    phi = 0.6
    pair = (np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0]]), np.array([[0, 1, 2], [1, 0, 3]]))
    m = Material()
    rest = ClothRest.from_cloth(make_cloth([pair], m))
    x = torch.tensor([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -math.cos(phi), math.sin(phi)]])
    coeff = m.bending_stiffness * 1.0**2 / (4 * (0.5 + 0.5))  # l = 1, A1 = A2 = 1/2
    assert math.isclose(bending_energy(x, rest).item(), coeff * phi**2 / 2, rel_tol=1e-5)


def test_bending_rest_angle_of_curved_rest():
    s = trimesh.creation.icosphere(subdivisions=2)
    rest = ClothRest.from_cloth(make_cloth([(s.vertices, s.faces)]))
    x = torch.as_tensor(s.vertices, dtype=torch.float32)
    assert bending_energy(x, rest).item() < 1e-12
    flat = ClothRest.from_cloth(make_cloth([(s.vertices, s.faces)]), flat_rest_bending=True)
    assert bending_energy(x, flat).item() > 0


def test_inertia_and_gravity():
    v, f = grid(3)
    cloth = make_cloth([(v, f)])
    cloth.pinned[0] = True
    rest = ClothRest.from_cloth(cloth)
    x = torch.as_tensor(v, dtype=torch.float32) + torch.tensor([0.0, 0.0, 2.0])
    vel = torch.tensor([0.01, -0.02, 0.03])
    assert inertia_energy(x - vel, x, x + vel, rest, 1 / 30).item() < 1e-12
    a = torch.tensor([0.0, 0.0, 0.002])
    free_mass = cloth.vertex_mass[1:].sum().item()
    expected = free_mass * 0.002**2 / (2 / 30**2)
    assert math.isclose(inertia_energy(x - vel, x, x + vel + a, rest, 1 / 30).item(), expected, rel_tol=1e-3)
    expected = (cloth.vertex_mass[1:] * GRAVITY * x[1:, 2]).sum().item()
    assert math.isclose(gravity_energy(x, rest).item(), expected, rel_tol=1e-6)


def two_sheets(gap: float = 0.01) -> tuple[ClothRest, torch.Tensor]:
    v, f = grid(3, size=0.02)
    rest = ClothRest.from_cloth(make_cloth([(v, f), (v + [0, 0, gap], f)]))
    return rest, rest_x(v, gap)


def rest_x(v: np.ndarray, gap: float) -> torch.Tensor:
    return torch.as_tensor(np.concatenate([v, v + [0, 0, gap]]), dtype=torch.float32)


def test_repulsion_zero_beyond_eps_and_cubic_inside():
    rest, x_cur = two_sheets(0.005)
    pairs = layer_pairs(x_cur, rest)
    assert len(pairs) == 9 and (pairs[:, 0] - pairs[:, 1] == 9).all()
    eps = 3e-3
    vals = []
    for z in [0.004, 0.0031, 0.002, 0.0, -0.001]:
        x = x_cur.clone()
        x[9:, 2] = z
        n = vertex_normals(x, rest.faces)
        vals.append(repulsion_energy(x, n, pairs, rest, eps=eps).item())
    assert vals[0] == 0.0 and vals[1] == 0.0
    for z, val in zip([0.002, 0.0, -0.001], vals[2:], strict=True):
        assert math.isclose(val, 9 * (eps - z) ** 3, rel_tol=1e-4)
    # pairs beyond the pairing radius at step t are dropped
    _, far = two_sheets(0.05)
    assert len(layer_pairs(far, rest)) == 0


def test_pre_layer_contact_loss_reads_the_prediction_before_the_layer():
    """The repulsion term on x̂ is the cubic of Eq. 25 times factor x λr; the body term the cubic penalty times
    factor x its weight; a factor of 0 leaves its term out; x_{t+1} plays no part."""
    rest, x_cur = two_sheets(0.005)
    pairs = layer_pairs(x_cur, rest)
    w = LossWeights(repulsion=8e4, collision=2e4, repulsion_eps=4.5e-3)
    x_hat = x_cur.clone()
    x_hat[9:, 2] = 0.001  # the outer sheet 1 mm in front of the inner one: 3.5 mm inside the clearance
    far_body = BodyStep.from_vertices(torch.tensor([[0.0, 0.0, -1.0]] * 3), torch.tensor([[0.0, 0.0, -1.0],
                                      [1.0, 0.0, -1.0], [0.0, 1.0, -1.0]]), torch.tensor([[0, 1, 2]]))
    loss, terms = pre_layer_contact_loss(x_hat, far_body, rest, w, repulsion_factor=0.5, pairs=pairs)
    assert set(terms) == {"pre_repulsion"}
    assert math.isclose(terms["pre_repulsion"], 9 * 0.0035**3, rel_tol=1e-4)
    assert math.isclose(loss.item(), 0.5 * 8e4 * 9 * 0.0035**3, rel_tol=1e-4)
    # the pairs are found from x_cur when not given
    again, _ = pre_layer_contact_loss(x_hat, far_body, rest, w, repulsion_factor=0.5, x_cur=x_cur)
    assert math.isclose(again.item(), loss.item(), rel_tol=1e-6)
    # the body term: a cloth vertex 1 cm inside a unit sphere
    s = trimesh.creation.icosphere(subdivisions=4)
    sphere = torch.as_tensor(s.vertices, dtype=torch.float32)
    body = BodyStep.from_vertices(sphere, sphere, torch.as_tensor(s.faces))
    v, f = grid(2, size=0.01)
    one = ClothRest.from_cloth(make_cloth([(v, f)]))
    inside = sphere[:4] / sphere[:4].norm(dim=-1, keepdim=True) * 0.99
    loss, terms = pre_layer_contact_loss(inside, body, one, w, repulsion_factor=1.0, collision_factor=2.0)
    assert set(terms) == {"pre_collision"}  # one layer: no repulsion term
    expected = 4 * (w.collision_eps + 0.01) ** 3
    assert math.isclose(terms["pre_collision"], expected, rel_tol=2e-2)
    assert math.isclose(loss.item(), 2.0 * 2e4 * terms["pre_collision"], rel_tol=1e-5)
    zero, none = pre_layer_contact_loss(inside, body, one, w)
    assert zero.item() == 0.0 and none == {}
    with pytest.raises(ValueError, match=">= 0"):
        pre_layer_contact_loss(inside, body, one, w, collision_factor=-1.0)


def test_collision_inside_and_outside_body():
    s = trimesh.creation.icosphere(subdivisions=4)
    body = torch.as_tensor(s.vertices, dtype=torch.float32)
    normals = vertex_normals(body, torch.as_tensor(s.faces))
    v, f = grid(2, size=0.01)
    rest = ClothRest.from_cloth(make_cloth([(v, f)]))
    dirs = body[:4] / body[:4].norm(dim=-1, keepdim=True)
    for r, expected in [(1.01, 0.0), (0.99, 4 * (COLLISION_EPS + 0.01) ** 3), (1.002, 4 * 0.001**3)]:
        e = collision_energy(dirs * r, body, normals, rest).item()
        assert math.isclose(e, expected, rel_tol=2e-2, abs_tol=1e-15), (r, e, expected)


def test_friction_contact_slip():
    s = trimesh.creation.icosphere(subdivisions=4)
    body = torch.as_tensor(s.vertices, dtype=torch.float32)
    normals = vertex_normals(body, torch.as_tensor(s.faces))
    v, f = grid(2, size=0.01)
    cloth = make_cloth([(v, f)])
    rest = ClothRest.from_cloth(cloth)
    top = torch.tensor([0.0, 0.0, 1.0])
    i_top = int(torch.argmax(body[:, 2]))
    x_cur = body[i_top].repeat(4, 1) + 0.001 * top
    move = torch.tensor([0.0, 0.0, 0.0])
    # body and cloth move together: no slip
    e = friction_energy(x_cur, x_cur + 0.01, body, body + 0.01, normals, rest)
    assert e.item() < 1e-12
    # tangential slip of 5 mm on a still body
    slip = torch.tensor([0.005, 0.0, 0.0])
    e = friction_energy(x_cur, x_cur + slip + move, body, body, normals, rest).item()
    c = 1e-4
    expected = 0.5 * GRAVITY * cloth.vertex_mass.sum().item() * (math.sqrt(0.005**2 + c * c) - c)
    assert math.isclose(e, expected, rel_tol=1e-3)
    # far from the body: no contact
    assert friction_energy(x_cur + 0.1 * top, x_cur + 0.1 * top + slip, body, body, normals, rest).item() == 0


def test_layer_friction_is_the_coulomb_work_of_the_slip_between_layers():
    """Outer sheet 4 mm above the inner one (in contact, radius 5 mm): sliding it 5 mm tangentially over a still
    inner sheet costs mu g m_outer (sqrt(s^2 + c^2) - c); both sheets moving together, a purely normal move, or a
    sheet 1 cm away cost nothing; the force is equal and opposite on the two layers."""
    rest, x_cur = two_sheets(0.004)
    pairs = layer_pairs(x_cur, rest)
    normals = vertex_normals(x_cur, rest.faces)
    slip = torch.zeros_like(x_cur)
    slip[9:, 0] = 0.005
    e = layer_friction_energy(x_cur, x_cur + slip, normals, pairs, rest).item()
    c = 1e-4
    m_outer = float(rest.mass[9:].sum())
    assert math.isclose(e, rest.material.friction * GRAVITY * m_outer * (math.sqrt(0.005**2 + c * c) - c), rel_tol=1e-4)
    together = torch.zeros_like(x_cur)
    together[:, 0] = 0.005
    assert layer_friction_energy(x_cur, x_cur + together, normals, pairs, rest).item() < 1e-12
    normal_move = torch.zeros_like(x_cur)
    normal_move[9:, 2] = -0.002
    assert layer_friction_energy(x_cur, x_cur + normal_move, normals, pairs, rest).item() < 1e-12
    far = x_cur.clone()
    far[9:, 2] = 0.01
    assert layer_friction_energy(far, far + slip, normals, pairs, rest).item() == 0.0
    x_next = (x_cur + slip).requires_grad_(True)
    layer_friction_energy(x_cur, x_next, normals, pairs, rest).backward()
    g = x_next.grad
    assert torch.allclose(g[9:].sum(0), -g[:9].sum(0), atol=1e-9) and float(g[9:, 0].sum()) > 0
    # total_loss adds it only when its weight is set, for the baseline weights too (repulsion 0)
    far_body = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0, -1], [0, 1.0, -1]])  # 1 m below: no body contact
    body = BodyStep.from_vertices(far_body, far_body, torch.tensor([[0, 1, 2]]))
    _, off = total_loss(x_cur, x_cur, x_cur + slip, body, rest, LossWeights(repulsion=0.0))
    _, on = total_loss(x_cur, x_cur, x_cur + slip, body, rest, LossWeights(repulsion=0.0, layer_friction=1.5))
    assert "layer_friction" not in off and math.isclose(on["layer_friction"], e, rel_tol=1e-5)


def test_layer_friction_normal_force_adds_the_lagged_repulsion_push():
    """With contact_stiffness k the normal force of a pair at gap d is m g + 3 k (eps - d)^2, the push of the
    repulsion term k (eps - d)^3 (Eq. 25), capped at d = 0 for an interpenetrated pair; beyond eps it is the weight
    alone, and the normal force carries no gradient (the slip does)."""
    k, eps, c, s = 1e4, 3e-3, 1e-4, 0.005
    for gap, push in ((0.001, 3 * k * (eps - 0.001) ** 2), (0.004, 0.0), (-0.002, 3 * k * eps**2)):
        rest, x_cur = two_sheets(0.004)
        x_cur[9:, 2] = gap
        pairs = layer_pairs(two_sheets(0.004)[1], rest)
        normals = vertex_normals(x_cur, rest.faces)
        slip = torch.zeros_like(x_cur)
        slip[9:, 0] = s
        mu, m = rest.material.friction, rest.mass[9:].double()
        expected = float((mu * (GRAVITY * m + push)).sum()) * (math.sqrt(s * s + c * c) - c)
        e = layer_friction_energy(x_cur, x_cur + slip, normals, pairs, rest, contact_stiffness=k, eps=eps)
        assert math.isclose(e.item(), expected, rel_tol=1e-4), (gap, e.item(), expected)
        weight_only = layer_friction_energy(x_cur, x_cur + slip, normals, pairs, rest).item()
        assert (weight_only < e.item()) == (push > 0)
    # total_loss uses the repulsion weight as k when asked to, and nothing changes without a repulsion term
    rest, x_cur = two_sheets(0.001)
    slip = torch.zeros_like(x_cur)
    slip[9:, 0] = s
    far_body = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0, -1], [0, 1.0, -1]])
    body = BodyStep.from_vertices(far_body, far_body, torch.tensor([[0, 1, 2]]))
    normals = vertex_normals(x_cur + slip, rest.faces)
    pairs = layer_pairs(x_cur, rest)
    on = total_loss(x_cur, x_cur, x_cur + slip, body, rest,
                    LossWeights(repulsion=k, layer_friction=1.5, layer_friction_contact=True))[1]
    assert math.isclose(on["layer_friction"], layer_friction_energy(
        x_cur, x_cur + slip, normals, pairs, rest, contact_stiffness=k).item(), rel_tol=1e-5)
    no_rep = total_loss(x_cur, x_cur, x_cur + slip, body, rest,
                        LossWeights(repulsion=0.0, layer_friction=1.5, layer_friction_contact=True))[1]
    assert math.isclose(no_rep["layer_friction"], layer_friction_energy(
        x_cur, x_cur + slip, normals, pairs, rest).item(), rel_tol=1e-5)


def test_layer_friction_contact_band_follows_the_repulsion_clearance():
    """The contact radius is the clearance + 2 mm: a sheet resting 6 mm out is outside the band at the default
    3 mm clearance (radius 5 mm) and inside it at a 4.5 mm one (radius 6.5 mm), where it costs the Coulomb work of
    its weight; an explicit radius (a fixed 5 mm, as sessions 27-29 trained) overrides it, in total_loss too."""
    from smln.losses.friction import LAYER_FRICTION_RADIUS, layer_friction_radius

    assert math.isclose(LAYER_FRICTION_RADIUS, 0.005) and math.isclose(layer_friction_radius(), 0.005)
    assert math.isclose(layer_friction_radius(0.0045), 0.0065)
    rest, x_cur = two_sheets(0.006)
    pairs = layer_pairs(x_cur, rest)
    normals = vertex_normals(x_cur, rest.faces)
    slip = torch.zeros_like(x_cur)
    slip[9:, 0] = 0.005
    c = 1e-4
    work = rest.material.friction * GRAVITY * float(rest.mass[9:].sum()) * (math.sqrt(0.005**2 + c * c) - c)
    assert layer_friction_energy(x_cur, x_cur + slip, normals, pairs, rest).item() == 0.0
    wide = layer_friction_energy(x_cur, x_cur + slip, normals, pairs, rest, eps=0.0045).item()
    assert math.isclose(wide, work, rel_tol=1e-4)
    assert layer_friction_energy(x_cur, x_cur + slip, normals, pairs, rest, eps=0.0045, radius=0.005).item() == 0.0
    far_body = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0, -1], [0, 1.0, -1]])
    body = BodyStep.from_vertices(far_body, far_body, torch.tensor([[0, 1, 2]]))
    follows = total_loss(x_cur, x_cur, x_cur + slip, body, rest,
                         LossWeights(repulsion=0.0, layer_friction=1.5, repulsion_eps=0.0045))[1]
    fixed_5mm = LossWeights(repulsion=0.0, layer_friction=1.5, repulsion_eps=0.0045, layer_friction_radius=0.005)
    fixed = total_loss(x_cur, x_cur, x_cur + slip, body, rest, fixed_5mm)[1]
    assert math.isclose(follows["layer_friction"], work, rel_tol=1e-4) and fixed["layer_friction"] == 0.0


def test_gradcheck_float64_tiny_mesh():
    pair = (np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0.1], [0.5, -1, 0.2]]), np.array([[0, 1, 2], [1, 0, 3]]))
    rest = ClothRest.from_cloth(
        make_cloth([pair], Material(lame_mu=1.0, lame_lambda=2.0, bending_stiffness=1.0))
    )
    rest = rest.to(dtype=torch.float64)
    x = torch.tensor(pair[0], dtype=torch.float64) * 1.1 + 0.05 * torch.randn(4, 3, dtype=torch.float64)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: stretch_energy(y, rest), (x,))
    assert torch.autograd.gradcheck(lambda y: bending_energy(y, rest), (x,))
    v, f = grid(3, size=0.02)
    rest2 = ClothRest.from_cloth(make_cloth([(v, f), (v + [0, 0, 0.005], f)])).to(dtype=torch.float64)
    xc = rest_x(v, 0.005).double()
    pairs = layer_pairs(xc, rest2)
    xn = (xc + torch.tensor([0, 0, -0.004], dtype=torch.float64) * (torch.arange(18) >= 9)[:, None]).detach()
    xn = (xn + 1e-4 * torch.randn_like(xn)).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda y: repulsion_energy(y, vertex_normals(y, rest2.faces), pairs, rest2), (xn,)
    )


def test_total_loss_two_layers_on_body():
    s = trimesh.creation.icosphere(subdivisions=4)
    body = torch.as_tensor(s.vertices, dtype=torch.float32)
    g1 = trimesh.creation.icosphere(subdivisions=3)
    cloth = make_cloth([(g1.vertices * 1.01, g1.faces), (g1.vertices * 1.02, g1.faces)])
    cloth.pinned[:5] = True
    rest = ClothRest.from_cloth(cloth)
    x = cloth.rest_vertices
    step = BodyStep.from_vertices(body, body + 0.001, torch.as_tensor(s.faces))
    x_next = (x + 0.001 + 0.002 * torch.randn_like(x)).requires_grad_(True)
    loss, terms = total_loss(x, x, x_next, step, rest)
    loss.backward()
    assert set(terms) == {
        "stretch",
        "bending",
        "gravity",
        "inertia",
        "collision",
        "friction",
        "repulsion",
        "total",
    }
    assert torch.isfinite(x_next.grad).all()
    w = LossWeights()
    assert math.isclose(
        terms["total"], sum(getattr(w, k) * v for k, v in terms.items() if k != "total"), rel_tol=1e-4
    )
    # pinned vertices only enter through stretch/bending; with those off their gradient is zero
    x_next.grad = None
    loss, _ = total_loss(x, x, x_next, step, rest, LossWeights(stretch=0, bending=0, repulsion=0))
    loss.backward()
    assert (x_next.grad[:5] == 0).all() and (x_next.grad[5:] != 0).any()


def test_total_loss_uses_the_collision_clearance_of_the_weights():
    s = trimesh.creation.icosphere(subdivisions=4)
    body = torch.as_tensor(s.vertices, dtype=torch.float32)
    v, f = grid(2, size=0.01)
    rest = ClothRest.from_cloth(make_cloth([(v, f)]))
    x = body[:4] / body[:4].norm(dim=-1, keepdim=True) * 1.004  # 4 mm outside the unit sphere
    step = BodyStep.from_vertices(body, body, torch.as_tensor(s.faces))
    only = dict(stretch=0, bending=0, gravity=0, friction=0, repulsion=0, inertia=0)
    _, default = total_loss(x, x, x, step, rest, LossWeights(**only))
    _, wide = total_loss(x, x, x, step, rest, LossWeights(**only, collision_eps=6e-3))
    assert default["collision"] == 0.0  # outside the 3 mm clearance
    assert math.isclose(wide["collision"], 4 * 0.002**3, rel_tol=3e-2)  # 2 mm inside a 6 mm clearance


def test_body_friction_contact_follows_the_collision_clearance():
    """A vertex resting 4 mm off the body is outside the default 3 mm contact band (no friction on its slip) and
    inside a 4.5 mm clearance, where the body penalty holds resting cloth: there it pays mu m g |slip|."""
    s = trimesh.creation.icosphere(subdivisions=4)
    body = torch.as_tensor(s.vertices, dtype=torch.float32)
    v, f = grid(2, size=0.01)
    cloth = make_cloth([(v, f)])
    rest = ClothRest.from_cloth(cloth)
    i_top = int(torch.argmax(body[:, 2]))
    x = body[i_top].repeat(4, 1) + torch.tensor([0.0, 0.0, 0.004])
    slip = torch.tensor([0.005, 0.0, 0.0])
    step = BodyStep.from_vertices(body, body, torch.as_tensor(s.faces))
    only = dict(stretch=0, bending=0, gravity=0, collision=0, repulsion=0, inertia=0)
    _, default = total_loss(x, x, x + slip, step, rest, LossWeights(**only))
    _, wide = total_loss(x, x, x + slip, step, rest, LossWeights(**only, collision_eps=4.5e-3))
    c = 1e-4
    expected = 0.5 * GRAVITY * cloth.vertex_mass.sum().item() * (math.sqrt(0.005**2 + c * c) - c)
    assert default["friction"] == 0.0
    assert math.isclose(wide["friction"], expected, rel_tol=1e-3)


def test_total_loss_uses_the_layer_clearance_of_the_weights():
    """Two sheets 4 mm apart: no repulsion with the default 3 mm clearance, (6 mm - 4 mm)^3 per pair with 6 mm."""
    rest, x = two_sheets(0.004)
    far_body = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0, -1], [0, 1.0, -1]])  # 1 m below: no body contact
    body = BodyStep.from_vertices(far_body, far_body, torch.tensor([[0, 1, 2]]))
    only = dict(stretch=0, bending=0, gravity=0, friction=0, collision=0, inertia=0, repulsion=1.0)
    _, default = total_loss(x, x, x, body, rest, LossWeights(**only))
    _, wide = total_loss(x, x, x, body, rest, LossWeights(**only, repulsion_eps=6e-3))
    assert default["repulsion"] == 0.0
    assert math.isclose(wide["repulsion"], 9 * 0.002**3, rel_tol=1e-3)
