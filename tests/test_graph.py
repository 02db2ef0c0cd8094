"""Multi-layer graph: edge counts, virtual/body edges, hierarchy, translation invariance of the features."""

import numpy as np
import pytest
import torch
from scipy.sparse import coo_matrix, csgraph

from smln.geometry import vertex_normals
from smln.graph import LEGACY_BODY_EDGE_DIM, NODE_DIM, GraphTopology, anchor_hierarchy, mesh_edges
from smln.graph.synthetic import capsule_body, rigid_lbs, sway_motion, tube, tube_outfit


@pytest.fixture(scope="module")
def scene():
    cloth = tube_outfit(radii=(0.12, 0.126), n_around=24, n_rings=10)
    bv, bf = capsule_body(radius=0.1, height=1.2, max_edge=0.03)
    tr = sway_motion(4)
    body = rigid_lbs(torch.as_tensor(bv), tr)
    xs = rigid_lbs(cloth.rest_vertices, tr)
    return cloth, body, xs, vertex_normals(body, torch.as_tensor(bf))


def test_mesh_edge_count_exact():
    na, nr = 24, 10
    _, f = tube(0.1, 0.3, na, nr)
    e = mesh_edges(f)
    unique = na * nr + 2 * na * (nr - 1)  # rings + verticals + diagonals
    assert e.shape == (2, 2 * unique)
    pairs = set(map(tuple, e.T.tolist()))
    assert all((j, i) in pairs for i, j in pairs)  # both directions


def test_topology_counts(scene):
    cloth, _, _, _ = scene
    topo = GraphTopology.from_cloth(cloth)
    per_layer = 24 * 10 + 2 * 24 * 9
    assert topo.mesh_edges.shape == (2, 2 * 2 * per_layer)
    # mesh edges stay within a layer
    li = cloth.layer_index
    assert torch.equal(li[topo.mesh_edges[0]], li[topo.mesh_edges[1]])
    assert int(topo.pinned.sum()) == 2 * 24


def test_hierarchy_shrinks_and_stays_connected():
    _, f = tube(0.1, 0.3, 32, 20)
    n = 32 * 20
    levels = anchor_hierarchy(mesh_edges(f), n, levels=3)
    sizes = [n] + [lv.num_nodes for lv in levels]
    assert all(b < a for a, b in zip(sizes[:-1], sizes[1:], strict=True))
    prev = n
    for lv in levels:
        m = lv.num_nodes
        adj = coo_matrix((np.ones(lv.edges.shape[1]), (lv.edges[0], lv.edges[1])), shape=(m, m))
        assert csgraph.connected_components(adj, directed=False)[0] == 1
        assert lv.parent.shape == (prev,) and lv.parent.min() == 0 and lv.parent.max() == m - 1
        assert np.all(lv.edges[0] != lv.edges[1])
        prev = m
    # nested: every level's nodes are nodes of the previous level
    assert set(levels[1].nodes) <= set(levels[0].nodes)
    # cached
    assert anchor_hierarchy(mesh_edges(f), n, levels=3) is levels


def test_hierarchy_per_component():
    _, f = tube(0.1, 0.3, 16, 8)
    f2 = np.concatenate([f, f + 16 * 8])
    lv = anchor_hierarchy(mesh_edges(f2), 2 * 16 * 8, levels=1)[0]
    m = lv.num_nodes
    adj = coo_matrix((np.ones(lv.edges.shape[1]), (lv.edges[0], lv.edges[1])), shape=(m, m))
    assert csgraph.connected_components(adj, directed=False)[0] == 2


def _components(edges: np.ndarray, m: int) -> int:
    adj = coo_matrix((np.ones(edges.shape[1]), (edges[0], edges[1])), shape=(m, m))
    return csgraph.connected_components(adj, directed=False)[0]


def test_hierarchy_default_quarter_cluster_edges():
    """Default: MIS anchors (~1/4 of the nodes per level), anchors joined when their clusters touch."""
    _, f = tube(0.1, 0.3, 32, 20)
    n = 32 * 20
    cur = mesh_edges(f)
    levels = anchor_hierarchy(cur, n, levels=3)
    prev, prev_nodes = n, np.arange(n)
    for lv in levels:
        m = lv.num_nodes
        assert 0.15 * prev <= m <= 0.35 * prev
        assert _components(lv.edges, m) == 1
        # every node pools to itself or to an adjacent anchor; anchors are never adjacent
        adj = coo_matrix((np.ones(cur.shape[1]), (cur[0], cur[1])), shape=(prev, prev)).tocsr()
        anchor_prev = np.searchsorted(prev_nodes, lv.nodes)
        assert np.array_equal(prev_nodes[anchor_prev], lv.nodes)
        a = anchor_prev[lv.parent]
        i = np.arange(prev)
        assert np.all((a == i) | (np.asarray(adj[i, a]).ravel() > 0))
        assert adj[anchor_prev][:, anchor_prev].nnz == 0
        # cluster adjacency: exactly the pairs of distinct parents joined by an edge of the level below
        ps, pr = lv.parent[cur[0]], lv.parent[cur[1]]
        want = {(a, b) for a, b in zip(ps, pr, strict=True) if a != b}
        assert set(zip(lv.edges[0], lv.edges[1], strict=True)) == want
        assert len(want) == lv.edges.shape[1]  # unique
        cur, prev, prev_nodes = lv.edges, m, lv.nodes
    assert anchor_hierarchy(mesh_edges(f), n, levels=3, rule="two_hop", anchors="bfs_even") is not levels


def test_hierarchy_two_hop_option_halves():
    _, f = tube(0.1, 0.3, 32, 20)
    n = 32 * 20
    levels = anchor_hierarchy(mesh_edges(f), n, levels=2, rule="two_hop", anchors="bfs_even")
    assert 0.4 * n <= levels[0].num_nodes <= 0.6 * n
    deg = [lv.edges.shape[1] / lv.num_nodes for lv in levels]
    default = anchor_hierarchy(mesh_edges(f), n, levels=2)
    assert all(lv.edges.shape[1] / lv.num_nodes < d for lv, d in zip(default, deg, strict=True))
    with pytest.raises(ValueError):
        anchor_hierarchy(mesh_edges(f), n, levels=2, rule="two_hop", anchors="mis")


def test_virtual_edges_link_nearest_pairs(scene):
    cloth, body, xs, normals = scene
    topo = GraphTopology.from_cloth(cloth, virtual_radius=0.05)
    g = topo.build(xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    n = 24 * 10
    s, r = g.virtual_edges
    # every vertex of both layers receives exactly one virtual edge from the other layer
    assert g.virtual_edges.shape[1] == 2 * n
    assert torch.equal(torch.sort(r).values, torch.arange(2 * n))
    li = cloth.layer_index
    assert torch.all(li[s] != li[r])
    # concentric tubes with identical sampling: the nearest vertex is the same (ring, angle) slot
    assert torch.equal(s % n, r % n)
    # repulsion pairs: outer receiver, inner sender
    i, j = g.repulsion_pairs
    assert torch.all(li[i] == 1) and torch.all(li[j] == 0) and i.numel() == n
    assert g.virtual_features.shape == (2 * n, 9)
    d = g.virtual_features[:, 3]
    assert torch.allclose(d, torch.full_like(d, 0.006), atol=1e-4)


def test_virtual_radius_cuts(scene):
    cloth, body, xs, normals = scene
    topo = GraphTopology.from_cloth(cloth, virtual_radius=0.003)
    g = topo.build(xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    assert g.virtual_edges.shape[1] == 0 and g.repulsion_pairs.shape == (2, 0)


def test_body_edges_and_features(scene):
    cloth, body, xs, normals = scene
    topo = GraphTopology.from_cloth(cloth, body_radius=0.03)
    g = topo.build(xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    assert g.node_features.shape == (cloth.num_vertices, NODE_DIM)
    assert g.mesh_features.shape == (topo.mesh_edges.shape[1], 12)
    assert g.body_features.shape[1] == 13
    # inner tube (2 cm off the body) has body edges, outer one (2.6 cm) mostly too; all within the radius
    assert g.body_receivers.numel() > 0
    assert torch.all(g.body_features[:, 3] <= 0.03 + 1e-6)
    assert torch.all(g.node_features[g.body_receivers, 23] == 1)
    assert torch.all(torch.isfinite(g.node_features))


def test_body_edge_normal_columns(scene):
    """The body normal columns: unit outward normals of the capsule, and the signed distance along them is the
    radial gap (inner tube 2 cm outside the 10 cm capsule); a vertex moved inside the body reads negative. A topology
    without body normals builds the first 9 columns alone, the same values, and needs no normals."""
    cloth, body, xs, normals = scene
    topo = GraphTopology.from_cloth(cloth, body_radius=0.03)
    g = topo.build(xs[1], xs[1], body[1], body[1], xs[1], body_normals_next=normals[1])  # a still frame
    n, sd = g.body_features[:, 9:12], g.body_features[:, 12]
    assert torch.allclose(n.norm(dim=-1), torch.ones(len(n)), atol=2e-3)  # vertex_normals normalises with an epsilon
    inner = cloth.layer_index[g.body_receivers] == 0
    assert inner.sum() > 100
    assert torch.all((sd[inner] > 0.012) & (sd[inner] < 0.028))  # 2 cm gap, nearest-vertex discretisation
    assert torch.allclose(sd, (g.body_features[:, 4:7] * n).sum(-1))
    inside = xs[1].clone()
    centre_axis = body[1].mean(0)
    v0 = int(g.body_receivers[inner][0])
    radial = inside[v0] - centre_axis
    radial[2] = 0.0
    inside[v0] -= 0.03 * radial / radial.norm()  # 1 cm inside the capsule wall
    gi = topo.build(xs[1], inside, body[1], body[1], xs[1], body_normals_next=normals[1])
    row = int(torch.nonzero(gi.body_receivers == v0)[0, 0])
    assert -0.015 < float(gi.body_features[row, 12]) < -0.005
    legacy = GraphTopology.from_cloth(cloth, body_radius=0.03, body_normals=False)
    gl = legacy.build(xs[1], xs[1], body[1], body[1], xs[1])
    assert gl.body_features.shape[1] == LEGACY_BODY_EDGE_DIM
    assert torch.equal(gl.body_features, g.body_features[:, :LEGACY_BODY_EDGE_DIM])
    with pytest.raises(ValueError, match="body_normals_next"):
        topo.build(xs[0], xs[1], body[1], body[2], xs[2])


def test_features_translation_invariant(scene):
    cloth, body, xs, normals = scene
    topo = GraphTopology.from_cloth(cloth)
    shift = torch.tensor([0.3, -0.2, 0.5])
    g0 = topo.build(xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    g1 = topo.build(xs[0] + shift, xs[1] + shift, body[1] + shift, body[2] + shift, xs[2] + shift,
                    body_normals_next=normals[2])
    for a, b in [(g0.node_features, g1.node_features), (g0.mesh_features, g1.mesh_features),
                 (g0.virtual_features, g1.virtual_features), (g0.body_features, g1.body_features)]:
        assert torch.allclose(a, b, atol=1e-5)
