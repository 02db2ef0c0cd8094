"""Garments and outfits: mass, topology, pins, rest-state penetration on every shape, posed skinning, user OBJs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from smln.body import BODY_SHAPES, lbs, load_body
from smln.body.skinning import world_orient_fk
from smln.garments import (
    GARMENT_TYPES,
    OUTFITS,
    SPECS,
    TRAINING_EDGE_LENGTH,
    Garment,
    GarmentError,
    build_garment,
    build_outfit,
    outfit_registry,
)
from smln.garments.meshops import boundary_loops, components, signed_gap, vertex_normals_np


def _body_planes(shape: str) -> tuple[np.ndarray, np.ndarray]:
    b = load_body(shape)
    v = b.rest_vertices.numpy().astype(np.float64)
    return v, vertex_normals_np(v, b.faces.numpy())


@pytest.mark.parametrize("garment_type", GARMENT_TYPES)
def test_garment_topology_mass_and_pins(garment_type: str) -> None:
    g = build_garment(garment_type)
    # Eq. 3: masses sum to density x area
    assert g.vertex_mass.sum() == pytest.approx(g.material.density * g.area(), rel=1e-5)
    assert g.vertex_mass.min() > 0
    # one component, the expected open boundaries, outward-consistent winding
    assert len(np.unique(components(g.faces, g.num_vertices))) == 1
    assert len(boundary_loops(g.faces)) == SPECS[garment_type].boundary_loops
    # near-uniform edges around the 2 cm target
    e = np.concatenate([g.faces[:, [0, 1]], g.faces[:, [1, 2]], g.faces[:, [2, 0]]])
    length = np.linalg.norm(g.vertices[e[:, 0]] - g.vertices[e[:, 1]], axis=1)
    assert 0.017 < np.median(length) < 0.023 and np.percentile(length, 1) > 0.008
    # skinning weights: 7 per vertex, rows sum to 1
    assert g.skin_indices.shape == (g.num_vertices, 7)
    np.testing.assert_allclose(g.skin_weights.sum(axis=1), 1.0, atol=1e-5)
    # pins: exactly the waist (top) boundary loop of lower-body garments, none for tops
    if SPECS[garment_type].pinned_waist:
        top = max(boundary_loops(g.faces), key=lambda lp: g.vertices[lp, 2].mean())
        assert set(np.flatnonzero(g.pinned)) == set(top.tolist())
    else:
        assert not g.pinned.any()


@pytest.mark.parametrize("shape", list(BODY_SHAPES))
def test_outfits_rest_state_has_no_penetration(shape: str) -> None:
    bv, bn = _body_planes(shape)
    h = 0.02 if shape == "female_average" else TRAINING_EDGE_LENGTH
    for name in OUTFITS:
        o = build_outfit(name, shape, h)
        cloth = o.to_cloth()
        assert cloth.num_layers == len(OUTFITS[name]) and cloth.num_vertices == o.num_vertices
        x = cloth.rest_vertices.numpy().astype(np.float64)
        assert (signed_gap(x, bv, bn) > 0).all(), f"{name} on {shape}: H-Coll > 0"
        for k, sl in enumerate(cloth.layer_slices()[1:], start=1):
            inner = cloth.layer_slices()[k - 1]
            fi = cloth.faces[(cloth.layer_index[cloth.faces[:, 0]] == k - 1)].numpy() - inner.start
            gap = signed_gap(x[sl], x[inner], vertex_normals_np(x[inner], fi))
            assert (gap > 0).all(), f"{name} on {shape}: L-Coll > 0 for layer {k}"


def test_split_holds_out_unseen_garment_types() -> None:
    reg = outfit_registry()
    train_types = {t for v in reg.values() if v["split"] == "train" for t in v["layers"]}
    unseen = [k for k, v in reg.items() if v["split"] == "test_unseen" and set(v["layers"]) - train_types]
    assert len(unseen) >= 2
    assert len(OUTFITS) >= 8 and all(2 <= len(v) <= 3 for v in OUTFITS.values())


def _leg_pose(body, degrees: float) -> torch.Tensor:
    """(1, B, 3, 4) T-pose -> posed transforms with both thighs rotated about X (one forward, one back)."""
    orient = body.tpose_orientations.clone()
    for leg, sign in (("LeftUpLeg", 1.0), ("RightUpLeg", -1.0)):
        a = np.radians(degrees) * sign
        rx = torch.tensor([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]], dtype=torch.float32)
        for b in body.descendants(leg):
            orient[b] = rx @ orient[b]
    anny = world_orient_fk(body.rest_bone_poses, body.bone_parents, orient[None], body.rest_bone_poses[None, 0, :3, 3])
    return anny, body.garment_transforms(anny)


# measured on female_average at +-30 deg thigh swing: trousers 0 %, t-shirt 0 %; the skirt's diffused weights do
# not follow the thigh (by design), so the swung thigh crosses its panel: 6.2 % / 7.9 % (the simulator resolves it)
INSIDE_BOUND = {"trousers": 0.03, "tshirt": 0.01, "skirt": 0.10}


@pytest.mark.parametrize("garment_type", list(INSIDE_BOUND))
def test_skinned_garment_stays_outside_posed_body(garment_type: str) -> None:
    body = load_body()
    g = build_garment(garment_type)
    for deg in (-30.0, 30.0):
        anny_tf, garment_tf = _leg_pose(body, deg)
        posed_body = lbs(body.anny_rest_vertices, body.skin_indices, body.skin_weights, anny_tf)[0].numpy()
        posed = lbs(torch.from_numpy(g.vertices), torch.from_numpy(g.skin_indices), torch.from_numpy(g.skin_weights),
                    garment_tf)[0].numpy()
        bn = vertex_normals_np(posed_body.astype(np.float64), body.faces.numpy())
        inside = (signed_gap(posed.astype(np.float64), posed_body.astype(np.float64), bn) < 0).mean()
        print(f"{garment_type} {deg:+.0f} deg: {inside:.2%} inside")
        assert inside < INSIDE_BOUND[garment_type], f"{garment_type} at {deg} deg: {inside:.1%} inside the body"
    if garment_type == "skirt":  # loose: the hem must not follow one leg
        hem = min(boundary_loops(g.faces), key=lambda lp: g.vertices[lp, 2].mean())
        dense = np.zeros((len(hem), body.num_bones))
        np.add.at(dense, (np.repeat(np.arange(len(hem)), 7), g.skin_indices[hem].ravel()), g.skin_weights[hem].ravel())
        legs = [body.bone_index(n) for n in ("LeftLeg", "RightLeg", "LeftFoot", "RightFoot")]
        assert dense[:, legs].sum(axis=1).max() < 0.3


def _write(path, text: str | bytes):
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)
    return path


def test_user_obj_roundtrip_and_layering(tmp_path) -> None:
    import trimesh

    base = build_outfit("tshirt_jacket", edge_length=TRAINING_EDGE_LENGTH)
    skirt = build_garment("skirt", edge_length=TRAINING_EDGE_LENGTH)
    path = tmp_path / "skirt.obj"
    trimesh.Trimesh(skirt.vertices, skirt.faces, process=False).export(path)
    g = Garment.from_obj(path, load_body())
    assert g.num_vertices == skirt.num_vertices and g.pinned.sum() == skirt.pinned.sum() > 0
    # a shirt shrunk inside the t-shirt is placed between body and jacket and pushed out of the t-shirt
    tee = build_garment("tshirt", edge_length=TRAINING_EDGE_LENGTH, offset=0.004)
    trimesh.Trimesh(tee.vertices, tee.faces, process=False).export(tmp_path / "tee.obj")
    user = Garment.from_obj(tmp_path / "tee.obj")
    assert not user.pinned.any()
    o = base.with_layer(user, index=1)
    assert [x.name for x in o.layers] == ["tshirt", "tee", "jacket"]
    assert all((gap > 0).all() for gap in o.layer_gaps()) and all((gap > 0).all() for gap in o.body_gaps())
    # a wrong explicit scale is caught with a hint
    trimesh.Trimesh(skirt.vertices * 100, skirt.faces, process=False).export(tmp_path / "cm.obj")
    with pytest.raises(GarmentError, match="centimetres"):
        Garment.from_obj(tmp_path / "cm.obj", scale=1.0)
    assert Garment.from_obj(tmp_path / "cm.obj", scale=0.01).num_vertices == skirt.num_vertices


@pytest.mark.parametrize("unit, turn, note", [
    (0.01, "y", "read in cm, turned from Y up to Z up"),  # Blender's OBJ default (Y up, -Z forward) in cm
    (0.001, "z", "read in mm"),
    (1.0, "y", "turned from Y up to Z up"),
    (1.0, "z", ""),
])
def test_user_obj_unit_and_up_axis_are_read_from_the_fit_to_the_body(tmp_path, unit, turn, note) -> None:
    """A shipped garment written in another unit and frame loads back onto the body where it was, and says so."""
    import trimesh

    from smln.garments.obj_import import UP_AXES

    for kind in ("tshirt", "skirt"):  # a tight and a loose garment
        ref = build_garment(kind, edge_length=TRAINING_EDGE_LENGTH)
        file_vertices = ref.vertices.astype(np.float64) @ UP_AXES[turn] / unit  # body -> file frame (inverse turn)
        path = tmp_path / f"{kind}.obj"
        trimesh.Trimesh(file_vertices, ref.faces, process=False).export(path)
        g = Garment.from_obj(path, load_body())
        np.testing.assert_allclose(g.vertices, ref.vertices, atol=1e-5)
        assert g.note == note and g.pinned.sum() == ref.pinned.sum()


def test_user_obj_off_the_body_is_refused(tmp_path) -> None:
    """A garment 1 m above the body (in every unit and axis tried) gets a clear error, not a floating cloth."""
    import trimesh

    ref = build_garment("tshirt", edge_length=TRAINING_EDGE_LENGTH)
    path = _write(tmp_path / "floating.obj", "")
    trimesh.Trimesh(ref.vertices + np.array([0.0, 0.0, 1.0]), ref.faces, process=False).export(path)
    with pytest.raises(GarmentError, match="T-pose") as err:
        Garment.from_obj(path)
    assert "\n" not in str(err.value)
    with pytest.raises(GarmentError, match="up axis"):
        Garment.from_obj(path, up_axis="x")


@pytest.mark.parametrize(
    "content, message",
    [
        ("", "empty"),
        (bytes(range(256)) * 40, "mesh"),
        ("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", "NaN"),
        ("v 0 0 0\nv 0.3 0 0\nv 0 0.3 0\nv 0 0 0.3\nv 0.3 0.3 0.3\nf 1 2 3\nf 1 2 4\nf 1 2 5\n", "non-manifold"),
        ("v 0 0 0\nv 0.3 0 0\nv 0 0.3 0\nv 1 1 1\nv 1.3 1 1\nv 1 1.3 1\nf 1 2 3\nf 4 5 6\n", "pieces"),
        (b"v 0.1 0.2 0.3\n" * 2_000_000 + b"f 1 2 3\n", "limit"),
    ],
    ids=["empty", "junk", "nan", "nonmanifold", "soup", "huge"],
)
def test_bad_obj_rejected(tmp_path, content, message: str) -> None:
    path = _write(tmp_path / "bad.obj", content)
    with pytest.raises(GarmentError, match=message) as err:
        Garment.from_obj(path)
    assert "\n" not in str(err.value)
