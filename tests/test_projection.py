"""Collision projection (smln.projection): analytic cases on a sphere and stacked tubes, and the rollout option."""

import numpy as np
import torch
import trimesh

from smln.geometry.mesh import vertex_normals
from smln.graph.synthetic import capsule_body, rigid_lbs, sway_motion, tube_outfit
from smln.losses.rest import ClothRest
from smln.metrics import frame_metrics
from smln.model import SMLN, SMLNConfig
from smln.projection import (
    BODY_CLEARANCE,
    BODY_MAX_DEPTH,
    LAYER_CLEARANCE,
    project,
    project_out_of_body,
    project_out_of_layers,
)
from smln.rollout import rollout


def _sphere(radius: float = 0.2) -> tuple[torch.Tensor, torch.Tensor]:
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    return torch.as_tensor(s.vertices, dtype=torch.float32), torch.as_tensor(s.faces, dtype=torch.int64)


def test_body_projection_moves_inside_points_to_the_clearance_and_leaves_others():
    body, faces = _sphere()
    normals = vertex_normals(body, faces)
    # points on the directions of body vertices 0-3: 1 cm inside, 1 cm outside, 1 cm inside but not free,
    # 3 cm inside (deeper than BODY_MAX_DEPTH: the nearest-vertex test is not trusted there)
    x = torch.stack([body[0] * (1 - 0.01 / 0.2), body[1] * (1 + 0.01 / 0.2), body[2] * (1 - 0.01 / 0.2),
                     body[3] * (1 - 0.03 / 0.2)])
    free = torch.tensor([True, True, False, True])
    assert BODY_MAX_DEPTH < 0.03
    y = project_out_of_body(x, body, faces, free)
    torch.testing.assert_close(y[3], x[3])
    d0 = float(((y[0] - body[0]) * normals[0]).sum())
    assert abs(d0 - BODY_CLEARANCE) < 1e-4  # moved along the vertex normal to the clearance
    torch.testing.assert_close(y[1], x[1])  # outside: untouched
    torch.testing.assert_close(y[2], x[2])  # pinned: untouched
    assert not torch.equal(x, y)  # a new tensor, the input is kept


def test_layer_projection_pushes_the_outer_tube_out_of_the_inner_one():
    cloth = tube_outfit(radii=(0.12, 0.126), n_around=32, n_rings=8, pin_top=False)
    rest = ClothRest.from_cloth(cloth)
    x = cloth.rest_vertices.clone()
    outer = rest.layer_slices[1]
    xy = x[outer, :2]
    # the lower half of the outer tube shrunk to 0.115 m: 5 mm inside the inner tube
    low = x[outer, 2] < x[outer, 2].median()
    x[outer.start + torch.nonzero(low).squeeze(1), :2] = xy[low] * (0.115 / 0.126)
    before = frame_metrics(x, np.zeros((1, 3), np.float32), rest, body_normals=np.ones((1, 3), np.float32))
    assert before.values["l_coll"] > 20.0
    y = project_out_of_layers(x, rest)
    after = frame_metrics(y, np.zeros((1, 3), np.float32), rest, body_normals=np.ones((1, 3), np.float32))
    assert after.values["l_coll"] == 0.0
    r = y[outer, :2].norm(dim=-1)
    # moved vertices sit just outside the inner tube (its radius 0.12 m plus the clearance, up to the
    # facet/normal discretisation of a 32-gon), the untouched ones keep their place
    assert float(r[low].min()) > 0.12 and float(r[low].max()) < 0.12 + LAYER_CLEARANCE + 2e-3
    torch.testing.assert_close(y[outer][~low], x[outer][~low])
    torch.testing.assert_close(y[rest.layer_slices[0]], x[rest.layer_slices[0]])  # the inner layer stays


def test_layer_projection_ignores_far_pairs():
    cloth = tube_outfit(radii=(0.12, 0.126), n_around=24, n_rings=6, pin_top=False)
    rest = ClothRest.from_cloth(cloth)
    x = cloth.rest_vertices.clone()
    outer = rest.layer_slices[1]
    x[outer, :2] *= 0.5  # 6 cm inside the inner tube: farther than LAYER_RADIUS, no information
    torch.testing.assert_close(project_out_of_layers(x, rest), x)


def test_projection_result_reports_moves():
    body, faces = _sphere()
    cloth = tube_outfit(radii=(0.19,), n_around=24, n_rings=6, height=0.1, z0=-0.05, pin_top=False)
    rest = ClothRest.from_cloth(cloth)
    res = project(cloth.rest_vertices, rest, body, faces)
    assert bool(res.moved.all())  # a 0.19 m tube at |z| <= 5 cm is inside the 0.2 m sphere everywhere
    assert float(res.displacement.max()) < 0.03
    fm = frame_metrics(res.x, body, rest, body_faces=faces)
    assert fm.values["h_coll"] == 0.0


def test_rollout_with_projection_reports_it_and_removes_body_penetration():
    cloth = tube_outfit(radii=(0.097, 0.104), n_around=24, n_rings=10)  # inner tube inside the 0.1 m capsule
    bv, bf = capsule_body(radius=0.1, height=1.2, max_edge=0.03)
    tr = sway_motion(8, amplitude=0.03, period=1.5, angle=0.1)
    seq = (rigid_lbs(torch.as_tensor(bv), tr), tr)
    torch.manual_seed(0)
    model = SMLN(SMLNConfig(latent_size=16, schedule=((0, 1), (1, 1), (0, 1))))
    plain = list(rollout(model, cloth, seq, bf, num_frames=6))
    proj = list(rollout(model, cloth, seq, bf, num_frames=6, project_body=True, project_layers=True))
    assert plain[0].metrics["h_coll"] > 10.0  # the skinned start penetrates
    for f in proj[2:]:
        assert f.metrics["projected_fraction"] > 0.0 and f.metrics["projection_max_mm"] > 0.0
        free_pen = f.body_penetration & ~cloth.pinned.numpy()
        assert free_pen.mean() < 0.02, f.index
        assert f.metrics["h_coll"] < plain[f.index].metrics["h_coll"]
    assert "projected_fraction" not in plain[3].metrics


def test_projection_leaves_non_finite_vertices_for_the_rollout_to_flag():
    body, faces = _sphere()
    x = torch.stack([body[0] * 0.95, torch.tensor([float("nan"), 0.0, 0.0])])
    y = project_out_of_body(x, body, faces, torch.tensor([True, True]))
    assert torch.isnan(y[1]).any() and torch.isfinite(y[0]).all()
    assert float(y[0].norm()) > float(x[0].norm())  # the finite one was still pushed out


def test_project_skips_a_diverged_frame():
    cloth = tube_outfit(radii=(0.12, 0.126), n_around=16, n_rings=4, pin_top=False)
    rest = ClothRest.from_cloth(cloth)
    x = cloth.rest_vertices.clone()
    x[3, 1] = float("inf")
    body, faces = _sphere()
    res = project(x, rest, body, faces, layers=True)
    assert res.x is x and not bool(res.moved.any())
