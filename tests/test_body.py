"""The body: shipped exports match anny, T-pose, watertightness, skinning invariants."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
import trimesh

from smln.body import BODY_SHAPES, lbs, load_body, world_orient_fk


@pytest.mark.parametrize("shape", list(BODY_SHAPES))
def test_tpose_is_closed_standing_and_arms_horizontal(shape):
    body = load_body(shape)
    v = body.rest_vertices.numpy()
    mesh = trimesh.Trimesh(v, body.faces.numpy(), process=False)
    assert mesh.is_watertight and mesh.volume > 0.02  # closed, outward, a human volume (m^3)
    assert abs(v[:, 2].min()) < 1e-4  # feet on the floor
    assert 1.4 < v[:, 2].max() < 2.0
    for arm, sign in (("LeftArm", 1.0), ("RightArm", -1.0)):
        b = body.bone_index(arm)
        axis = body.tpose_orientations[b] @ torch.tensor([0.0, 1.0, 0.0])
        assert torch.allclose(axis, torch.tensor([sign, 0.0, 0.0]), atol=1e-5)
    # hands are the farthest points sideways: arms stretched out
    assert v[:, 0].max() > 0.6 and v[:, 0].min() < -0.6


def test_identity_world_orientations_give_anny_rest_mesh(body):
    rest = body.rest_bone_poses
    tf = world_orient_fk(rest, body.bone_parents, rest[None, :, :3, :3], rest[None, 0, :3, 3])
    posed = lbs(body.anny_rest_vertices, body.skin_indices, body.skin_weights, tf)[0]
    assert torch.allclose(posed, body.anny_rest_vertices, atol=1e-5)


def test_lbs_of_a_rigid_transform_moves_points_rigidly(body):
    angle = 0.7
    rot = torch.tensor([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0, 0, 1.0]])
    tf = torch.cat([rot, torch.tensor([[0.1], [0.2], [0.3]])], dim=1).float()
    tf = tf.expand(1, body.num_bones, 3, 4)
    pts = body.rest_vertices[:100]
    out = lbs(pts, body.skin_indices[:100], body.skin_weights[:100], tf)[0]
    assert torch.allclose(out, pts @ rot.T.float() + torch.tensor([0.1, 0.2, 0.3]), atol=1e-5)


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("SMLN_SKIP_ANNY") == "1", reason="anny cache not built")
def test_shipped_export_matches_anny():
    from smln.body.export import build_export, export_path

    fresh = build_export("female_average")
    shipped = np.load(export_path("female_average"))
    for key in ("rest_vertices", "rest_bone_poses"):
        np.testing.assert_allclose(fresh[key], shipped[key], atol=1e-5)
    np.testing.assert_array_equal(fresh["faces"], shipped["faces"])
    # skinning weights as per-vertex bone -> weight maps: the order of the K slots is not part of the contract
    # (equal weights can come out of anny's sort in either order on another CPU)
    from smln.garments.skin_transfer import dense_weights

    bones = int(max(fresh["skin_indices"].max(), shipped["skin_indices"].max())) + 1
    np.testing.assert_allclose(dense_weights(fresh["skin_indices"], fresh["skin_weights"], bones),
                               dense_weights(shipped["skin_indices"], shipped["skin_weights"], bones), atol=1e-5)
