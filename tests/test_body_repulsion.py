"""The body stage of the repulsion layer (``SMLNConfig.body_repulsion``): analytic pushes, the depth window,
config rules, the migration from a model without it and the checkpoint round trip."""

import pytest
import torch

from smln.checkpoint import load_checkpoint, save_checkpoint
from smln.geometry import vertex_normals
from smln.graph.synthetic import capsule_body, rigid_lbs, sway_motion, tube_outfit
from smln.model import SMLN, RepulsionLayer, SMLNConfig
from smln.model.migrate import add_body_repulsion
from smln.model.smln import BODY_REPULSION_MAX_DEPTH


def small_config(**kw):
    base = dict(latent_size=16, schedule=((0, 1), (1, 1), (2, 1), (1, 1), (0, 1)))
    base.update(kw)
    return SMLNConfig(**base)


def projection_models(cloth, pairing):
    """Two models with the same weights, body stage initialised as the projection (4 mm threshold): one reading
    "edge", one reading ``pairing``; and the outfit's topology."""
    torch.manual_seed(0)
    edge = SMLN(small_config(body_repulsion=True, body_repulsion_threshold=0.004)).eval()
    edge.body_repulsion.init_as_projection()
    other = SMLN(small_config(body_repulsion=True, body_repulsion_threshold=0.004, body_pairing=pairing)).eval()
    other.load_state_dict(edge.state_dict())
    return edge, other, other.make_topology(cloth)


def test_projection_init_pushes_exactly_to_the_threshold():
    """softplus(MLP) = 1: a garment vertex at signed distance e < threshold moves by (threshold - e) along n."""
    layer = RepulsionLayer(threshold=0.003, max_depth=0.02)
    layer.init_as_projection()
    with pytest.raises(ValueError):
        layer.init_as_projection(0.0)
    n = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, 0.9]]), dim=-1).expand(4, 3)
    depth = torch.tensor([-0.005, 0.001, 0.004, -0.03])  # 5 mm inside, 1 mm outside, beyond thr, beyond max depth
    inner = torch.zeros(4, 3)
    outer = inner + depth[:, None] * n
    a, ex = layer.push(torch.arange(4), outer, outer, inner, inner, n, 4)
    assert torch.allclose(a[0], 0.008 * n[0], atol=1e-7)
    assert torch.allclose(a[1], 0.002 * n[1], atol=1e-7)
    assert torch.count_nonzero(a[2:]) == 0
    assert ex["active"].tolist() == [0, 1]
    assert torch.allclose(ex["signed_distance"], depth, atol=1e-7)
    # after the push both vertices sit on the threshold plane
    assert torch.allclose(((outer[:2] + a[:2]) * n[:2]).sum(-1), torch.full((2,), 0.003), atol=1e-7)


def test_push_sums_pairs_on_a_shared_vertex_and_layer_forward_is_unchanged():
    layer = RepulsionLayer(threshold=0.005)
    torch.manual_seed(1)
    x = torch.randn(6, 3) * 0.003
    n = torch.nn.functional.normalize(torch.randn(6, 3), dim=-1)
    pairs = torch.tensor([[3, 3, 4], [0, 1, 2]])
    a, ex = layer(x, x, n, pairs)
    a_push, _ = layer.push(pairs[0], x[pairs[0]], x[pairs[0]], x[pairs[1]], x[pairs[1]], n[pairs[1]], 6)
    assert torch.equal(a, a_push)
    assert ex["active_pairs"].shape[0] == 2
    assert torch.count_nonzero(a[[0, 1, 2, 5]]) == 0


def test_config_rules():
    with pytest.raises(ValueError, match="body_repulsion"):
        SMLNConfig(body_repulsion=True, use_repulsion_layer=False)
    with pytest.raises(ValueError, match="body_repulsion"):
        SMLNConfig(body_repulsion=True, body_normal_features=False)
    with pytest.raises(ValueError, match="threshold"):
        SMLNConfig(body_repulsion=True, body_repulsion_threshold=0.0)
    cfg = SMLNConfig(body_repulsion=True, body_repulsion_threshold=0.002)
    assert SMLNConfig.from_dict(cfg.to_dict()) == cfg
    assert not hasattr(SMLN(SMLNConfig()), "body_repulsion")  # off by default: no extra weights


@pytest.fixture(scope="module")
def tight_scene():
    """A tube 3 mm outside a capsule body, moved into it by half a centimetre at the next frame: the body stage
    sees vertices inside the body."""
    cloth = tube_outfit(radii=(0.103, 0.125), n_around=24, n_rings=10)
    bv, bf = capsule_body(radius=0.1, height=1.2, max_edge=0.03)
    tr = sway_motion(4)
    body = rigid_lbs(torch.as_tensor(bv), tr)
    return cloth, body, rigid_lbs(cloth.rest_vertices, tr), vertex_normals(body, torch.as_tensor(bf))


def test_body_stage_pushes_inner_layer_out_of_the_body(tight_scene):
    cloth, body, xs, normals = tight_scene
    torch.manual_seed(0)
    old = SMLN(small_config()).eval()
    new = SMLN(small_config(body_repulsion=True, body_repulsion_threshold=0.004)).eval()
    add_body_repulsion(old, new)
    topo = new.make_topology(cloth)
    shift = torch.tensor([0.006, 0.0, 0.0])  # every vertex moves 6 mm along +x: the -x side enters the body
    with torch.no_grad():
        p0, a0, ex0 = old.step(topo, xs[1] - shift, xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
        p1, a1, ex1 = new.step(topo, xs[1] - shift, xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    assert torch.equal(p0, p1)  # the network's own prediction is untouched
    rb = ex1["body_repulsion"]
    pushed = rb["active_vertices"]
    assert pushed.numel() > 0
    # every free pushed vertex ends on the threshold plane of its body edge's vertex at t+1 (projection init)
    g = ex1["graph"]
    q, f = g.body_receivers, g.body_features
    b_next, n = g.x_cur[q] - f[:, 4:7], f[:, 9:12]
    x_hat = ex1["x_hat"]
    e = ((x_hat[q] - b_next) * n).sum(-1)
    assert torch.allclose(rb["signed_distance"], e, atol=1e-6)
    free = ~cloth.pinned[q]
    hit = (e < 0.004) & (e > -BODY_REPULSION_MAX_DEPTH) & free
    assert hit.sum() > 10 and (e[hit] < 0).any()  # the shift put some of them inside the body
    after = ((x_hat[q] + rb["a"][q] - b_next) * n).sum(-1)
    assert (after[hit] - 0.004).abs().max() < 2e-5  # the body normals are unit to 1e-3 at the capsule poles
    assert torch.count_nonzero(rb["a"][~torch.isin(torch.arange(cloth.num_vertices), pushed)]) == 0
    assert torch.count_nonzero(rb["a"][cloth.pinned]) == 0
    # the body push is part of the returned repulsion acceleration and of x_next
    assert torch.allclose(ex1["x_next"][~cloth.pinned], (x_hat + a1)[~cloth.pinned])


def test_add_body_repulsion_copies_every_weight_and_round_trips(tmp_path, tight_scene):
    torch.manual_seed(0)
    old = SMLN(small_config())
    new = SMLN(small_config(body_repulsion=True))
    add_body_repulsion(old, new, push_fraction=0.5)
    feats = torch.randn(7, 4)
    assert torch.allclose(torch.nn.functional.softplus(new.body_repulsion.mlp(feats)), torch.full((7, 1), 0.5))
    for k, v in old.state_dict().items():
        assert torch.equal(new.state_dict()[k], v), k
    with pytest.raises(ValueError, match="body stage"):
        add_body_repulsion(old, SMLN(small_config(body_repulsion=True, latent_size=8)))
    with pytest.raises(ValueError):
        add_body_repulsion(new, new)
    save_checkpoint(tmp_path / "ck", new, card={"variant": "full"})
    loaded, card = load_checkpoint(tmp_path / "ck")
    assert card["config"]["body_repulsion"] is True
    for k, v in new.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k


def test_nearest_body_pairing_reads_the_body_vertex_nearest_to_the_prediction(tight_scene):
    """body_pairing "nearest": every free garment vertex within the body radius of the body at t+1 is read against
    the body vertex nearest to its x̂ (found here by scipy's KD-tree, independently), and the projection-initialised
    stage puts each one inside the depth window exactly on that vertex's threshold plane; same weights as "edge"."""
    from scipy.spatial import cKDTree

    cloth, body, xs, normals = tight_scene
    edge, nearest, topo = projection_models(cloth, "nearest")
    shift = torch.tensor([0.006, 0.0, 0.0])  # every vertex moves 6 mm along +x: the -x side enters the body
    with torch.no_grad():
        pe, _, exe = edge.step(topo, xs[1] - shift, xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
        pn, an, exn = nearest.step(topo, xs[1] - shift, xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    assert torch.equal(pe, pn)  # the network's prediction is the same; only the stage's pairing differs
    x_hat = exn["x_hat"]
    dist, idx = cKDTree(body[2].numpy()).query(x_hat.numpy())
    idx = torch.as_tensor(idx)
    e = ((x_hat - body[2][idx]) * normals[2][idx]).sum(-1)
    free = ~cloth.pinned
    hit = torch.as_tensor(dist < 0.03) & (e < 0.004) & (e > -BODY_REPULSION_MAX_DEPTH) & free
    assert hit.sum() > 10 and (e[hit] < 0).any()
    a_body = exn["body_repulsion"]["a"]
    after = ((x_hat + a_body - body[2][idx]) * normals[2][idx]).sum(-1)
    assert (after[hit] - 0.004).abs().max() < 2e-5
    assert torch.count_nonzero(a_body[~hit]) == 0
    window = torch.as_tensor(dist < 0.03) & (e < 0.004) & (e > -BODY_REPULSION_MAX_DEPTH)  # pinned rows too, their
    assert sorted(exn["body_repulsion"]["active_vertices"].tolist()) == torch.nonzero(window).flatten().tolist()
    assert torch.count_nonzero(a_body[cloth.pinned]) == 0  # push is masked (as with the edge pairing)
    # the edge reading (nearest body vertex at t) pushes another set here: the pairing is what changed
    assert sorted(exe["body_repulsion"]["active_vertices"].tolist()) != sorted(
        exn["body_repulsion"]["active_vertices"].tolist())
    # a NaN prediction row is no pair; the others are unchanged
    from smln.model.smln import nearest_body_pairs

    g = exn["graph"]
    q, r = nearest_body_pairs(g, x_hat, 0.03)
    bad = x_hat.clone()
    bad[int(q[0])] = float("nan")
    q2, r2 = nearest_body_pairs(g, bad, 0.03)
    assert q2.tolist() == q[1:].tolist() and r2.tolist() == r[1:].tolist()
    # a KD-tree the caller already has (the rollout's, the training step's) gives the same pairs
    import dataclasses

    from smln.geometry import build_tree

    q3, r3 = nearest_body_pairs(dataclasses.replace(g, body_tree_next=build_tree(body[2])), x_hat, 0.03)
    assert torch.equal(q3, q) and torch.equal(r3, r)


def test_body_pairing_config_and_override():
    from smln.evaluate import apply_body_pairing
    from smln.model.smln import WEIGHTLESS_FIELDS

    with pytest.raises(ValueError, match="body_pairing"):
        SMLNConfig(body_repulsion=True, body_pairing="farthest")
    cfg = SMLNConfig(body_repulsion=True, body_pairing="nearest")
    assert SMLNConfig.from_dict(cfg.to_dict()) == cfg
    cfg = SMLNConfig(body_repulsion=True, body_pairing="edge_inside")
    assert SMLNConfig.from_dict(cfg.to_dict()) == cfg
    assert "body_pairing" in WEIGHTLESS_FIELDS
    model = SMLN(small_config(body_repulsion=True))
    assert model.config.body_pairing == "edge"  # the default: as every stage was trained
    assert apply_body_pairing(model, "nearest") and model.config.body_pairing == "nearest"
    assert not apply_body_pairing(model, "nearest") and not apply_body_pairing(model, None)
    without = SMLN(small_config())  # no body stage: nothing to change
    assert not apply_body_pairing(without, "nearest") and without.config.body_pairing == "edge"


def test_edge_inside_pairing_adds_the_nearest_reading_only_for_vertices_left_inside(tight_scene):
    """body_pairing "edge_inside": the edge pairs push exactly as with "edge"; then every free garment vertex that
    push leaves behind the tangent plane of its nearest body vertex at t+1 (found here by scipy's KD-tree,
    independently) is pushed by the same MLP against that vertex (projection init: onto its threshold plane), and
    no other vertex moves."""
    from scipy.spatial import cKDTree

    cloth, body, xs, normals = tight_scene
    edge, both, topo = projection_models(cloth, "edge_inside")
    # at t the garment sits 4 cm off to +x (its +x side deep in the body, beyond every body edge's reach) and moves
    # back 4.6 cm in the step: x̂ puts the +x side 6 mm inside, where no body edge of step t reads it
    far, back = torch.tensor([0.04, 0.0, 0.0]), torch.tensor([0.046, 0.0, 0.0])
    x_cur, x_prev = xs[1] + far, xs[1] + far + back
    with torch.no_grad():
        pe, _, exe = edge.step(topo, x_prev, x_cur, body[1], body[2], xs[2], body_normals_next=normals[2])
        pb, _, exb = both.step(topo, x_prev, x_cur, body[1], body[2], xs[2], body_normals_next=normals[2])
    assert torch.equal(pe, pb)
    x_hat, a_edge, a_both = exb["x_hat"], exe["body_repulsion"]["a"], exb["body_repulsion"]["a"]
    x1 = x_hat + a_edge  # where the edge pairs' push leaves each vertex
    dist, idx = cKDTree(body[2].numpy()).query(x1.numpy())
    idx = torch.as_tensor(idx)
    e1 = ((x1 - body[2][idx]) * normals[2][idx]).sum(-1)
    inside = torch.as_tensor(dist < 0.03) & (e1 < 0) & (e1 > -BODY_REPULSION_MAX_DEPTH) & ~cloth.pinned
    assert inside.sum() > 0  # the edge reading leaves vertices inside: the case the second pass is for
    assert torch.equal(a_both[~inside], a_edge[~inside])  # nothing else changes
    after = ((x_hat + a_both - body[2][idx]) * normals[2][idx]).sum(-1)
    assert (after[inside] - 0.004).abs().max() < 2e-5  # each one onto its nearest vertex's threshold plane
    pushed = exb["body_repulsion"]["active_vertices"]
    assert set(torch.nonzero(inside).flatten().tolist()) <= set(pushed.tolist())
    assert pushed.numel() == exb["body_repulsion"]["magnitude"].numel()
    # with nothing inside after the edge push, the reading is the edge reading exactly
    with torch.no_grad():
        _, _, exe0 = edge.step(topo, xs[1], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
        _, _, exb0 = both.step(topo, xs[1], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    x0 = exe0["x_hat"] + exe0["body_repulsion"]["a"]
    d0, i0 = cKDTree(body[2].numpy()).query(x0.numpy())
    e0 = ((x0 - body[2][torch.as_tensor(i0)]) * normals[2][torch.as_tensor(i0)]).sum(-1)
    assert not (torch.as_tensor(d0 < 0.03) & (e0 < 0) & ~cloth.pinned).any()
    assert torch.equal(exb0["body_repulsion"]["a"], exe0["body_repulsion"]["a"])


def test_inside_body_pairs_keeps_only_vertices_behind_the_nearest_tangent_plane(tight_scene):
    from scipy.spatial import cKDTree

    from smln.model.smln import inside_body_pairs

    cloth, body, xs, normals = tight_scene
    model = SMLN(small_config(body_repulsion=True, body_pairing="edge_inside")).eval()
    topo = model.make_topology(cloth)
    with torch.no_grad():
        _, _, ex = model.step(topo, xs[1], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    x = xs[2] - torch.tensor([0.01, 0.0, 0.0])  # the +x side moved 1 cm into the body
    q, r = inside_body_pairs(ex["graph"], x, 0.03)
    dist, idx = cKDTree(body[2].numpy()).query(x.numpy())
    e = ((x - body[2][torch.as_tensor(idx)]) * normals[2][torch.as_tensor(idx)]).sum(-1)
    expected = torch.nonzero(torch.as_tensor(dist < 0.03) & (e < 0)).flatten()
    assert expected.numel() > 0 and torch.equal(q, expected)
    assert torch.equal(r, torch.as_tensor(idx)[expected])
