"""Anchor hierarchy of a garment mesh for down/up-sampling in the processor (paper §3.2, after HOOD's scheme).

Anchor choice (``anchors``), per level, on the graph of the level below:

- ``"mis"`` (default): a maximal independent set of that graph (Luby rounds with a fixed pseudo-random
  priority, so deterministic): no two anchors are adjacent and every node is adjacent to an anchor, which it
  pools to (its nearest anchor, ``csgraph.dijkstra(min_only=True)``). On a triangle mesh this keeps ~1/4 of
  the nodes per level and halves the hop diameter, like a 2-D coarsening should.
- ``"bfs_even"`` (HOOD): per connected component, breadth-first search from a central node, keep the nodes
  at even BFS distance; every odd-distance node pools to its BFS parent. This keeps whole BFS rings, i.e.
  about HALF the nodes per level, not a quarter (repeating it on the quotient graph collapses a 5k-vertex
  outfit to one node per component by the third level, measured).

Coarse connectivity (``rule``):

- ``"cluster"`` (default): anchors a, b are joined when their clusters touch, i.e. some edge of the graph
  being coarsened joins a node pooled to a and a node pooled to b (the quotient graph). Each cluster is
  connected, so every level stays connected per component; degrees stay mesh-like (~5-6).
- ``"two_hop"`` (HOOD, needs ``anchors="bfs_even"``): kept nodes at most two hops apart (``A + A^2``
  restricted to the kept nodes). The coarse graphs get denser level after level (degrees ~9, 14, 22 on a
  2-layer 5k-vertex outfit), which made the coarse levels cost about as much as the fine mesh.

Level 0 is the fine mesh itself. For a level ``k >= 1``:

- ``nodes``: (N_k,) indices into the fine mesh (a subset of level ``k-1``'s nodes);
- ``edges``: (2, E_k) local indices into ``nodes`` (both directions, no self loops);
- ``parent``: (N_{k-1},) local index into level ``k``'s nodes of the anchor each level-``k-1`` node pools to
  (pool fine -> coarse = mean over the nodes sharing a parent; unpool coarse -> fine = gather by parent).

Everything is computed with scipy.sparse / csgraph (no Python loop over vertices) and cached per topology.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph


@dataclass(frozen=True)
class HierarchyLevel:
    """One level of the anchor hierarchy (see module docstring for the index conventions).

    Attributes:
        nodes: (N_k,) int64 indices into the fine mesh.
        edges: (2, E_k) int64 local indices into ``nodes``, both directions.
        parent: (N_{k-1},) int64 local index into ``nodes`` for every node of the previous level.
    """

    nodes: np.ndarray
    edges: np.ndarray
    parent: np.ndarray

    @property
    def num_nodes(self) -> int:
        return int(self.nodes.shape[0])


def _adjacency(edges: np.ndarray, n: int) -> sp.csr_matrix:
    """Symmetric boolean adjacency (n, n) of an edge list (2, E)."""
    data = np.ones(edges.shape[1], dtype=np.int8)
    a = sp.coo_matrix((data, (edges[0], edges[1])), shape=(n, n)).tocsr()
    a = ((a + a.T) > 0).astype(np.int8)
    a.setdiag(0)
    a.eliminate_zeros()
    return a


def _central_nodes(adj: sp.csr_matrix, labels: np.ndarray, ncomp: int) -> np.ndarray:
    """One approximately central node per connected component (double-sweep heuristic).

    Sweep 1 from the lowest index of each component finds a far node ``a``; sweep 2 from ``a`` finds ``b``;
    the centre is the node minimising ``max(d_a, d_b)`` (ties -> lowest index).

    Returns:
        (ncomp,) int64 node indices.
    """
    n = adj.shape[0]
    first = np.full(ncomp, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n))

    def sweep(sources: np.ndarray) -> np.ndarray:
        d = csgraph.shortest_path(adj, unweighted=True, indices=sources, directed=False)
        d = np.where(np.isfinite(d), d, -1.0).max(axis=0)  # each node is reached from its own source only
        return d

    def farthest(d: np.ndarray) -> np.ndarray:
        best = np.full(ncomp, -1.0)
        np.maximum.at(best, labels, d)
        cand = np.where(d == best[labels], np.arange(n), n)
        out = np.full(ncomp, n, dtype=np.int64)
        np.minimum.at(out, labels, cand)
        return out

    a = farthest(sweep(first))
    da = sweep(a)
    b = farthest(da)
    db = sweep(b)
    ecc = np.maximum(da, db)
    worst = np.full(ncomp, np.inf)
    np.minimum.at(worst, labels, ecc)
    cand = np.where(ecc == worst[labels], np.arange(n), n)
    centre = np.full(ncomp, n, dtype=np.int64)
    np.minimum.at(centre, labels, cand)
    return centre


COARSE_EDGE_RULES = ("cluster", "two_hop")


def check_rules(rule: str, anchors: str) -> None:
    """Raise ``ValueError`` on an unknown or unsupported (rule, anchors) pair."""
    if rule not in COARSE_EDGE_RULES:
        raise ValueError(f"coarse edge rule must be one of {COARSE_EDGE_RULES}, got {rule!r}")
    if anchors not in ANCHOR_RULES:
        raise ValueError(f"anchor rule must be one of {ANCHOR_RULES}, got {anchors!r}")
    if rule == "two_hop" and anchors != "bfs_even":
        raise ValueError("coarse_edges='two_hop' needs anchors='bfs_even' (MIS anchors 3 hops apart would be cut)")


def _quotient_edges(adj: sp.csr_matrix, parent: np.ndarray, n_c: int) -> np.ndarray:
    """(2, E_c) edges between anchors whose clusters touch (both directions, no self loops, unique)."""
    a = adj.tocoo()
    ps, pr = parent[a.row], parent[a.col]
    m = ps != pr
    q = sp.coo_matrix((np.ones(int(m.sum()), np.int8), (ps[m], pr[m])), shape=(n_c, n_c)).tocsr()
    q.sum_duplicates()
    q = q.tocoo()
    return np.stack([q.row, q.col]).astype(np.int64)


ANCHOR_RULES = ("mis", "bfs_even")


def _mis_anchors(adj: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Maximal independent set of ``adj`` and each node's anchor (itself or an adjacent anchor).

    Returns:
        kept (N_c,) int64 node indices, parent (n,) int64 index into ``kept``.
    """
    n = adj.shape[0]
    prio = np.random.default_rng(0).permutation(n).astype(np.int64) + 1  # unique, > 0
    state = np.zeros(n, np.int8)  # 0 undecided, 1 anchor, 2 covered
    while (state == 0).any():
        p = np.where(state == 0, prio, 0)
        nb_max = np.asarray(adj.multiply(p[None, :]).max(axis=1).todense()).ravel()
        sel = (state == 0) & (p > nb_max)
        state[sel] = 1
        covered = (adj @ sel.astype(np.int8)) > 0
        state[(state == 0) & covered] = 2
    kept = np.flatnonzero(state == 1).astype(np.int64)
    _, _, src = csgraph.dijkstra(
        adj, directed=False, indices=kept, unweighted=True, min_only=True, return_predecessors=True
    )
    local = np.full(n, -1, dtype=np.int64)
    local[kept] = np.arange(kept.size)
    return kept, local[np.asarray(src, dtype=np.int64)]


def coarsen(
    edges: np.ndarray, n: int, rule: str = "cluster", anchors: str = "mis"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One coarsening step of a graph.

    Args:
        edges: (2, E) int edge list over ``n`` nodes (any direction, duplicates allowed).
        n: number of nodes.
        rule: coarse connectivity, ``"cluster"`` or ``"two_hop"`` (module docstring).
        anchors: anchor choice, ``"mis"`` or ``"bfs_even"`` (module docstring).

    Returns:
        kept: (N_c,) int64 local indices of the kept nodes (anchors).
        coarse_edges: (2, E_c) int64 edges between kept nodes (``rule``), indices into ``kept``, both
            directions, no self loops.
        parent: (n,) int64 index into ``kept`` of each node's anchor (itself if kept).
    """
    check_rules(rule, anchors)
    adj = _adjacency(edges, n)
    if anchors == "mis":
        kept, parent = _mis_anchors(adj)
        return kept, _quotient_edges(adj, parent, kept.size), parent
    ncomp, labels = csgraph.connected_components(adj, directed=False)
    centres = _central_nodes(adj, labels, ncomp)
    dist, pred = csgraph.shortest_path(
        adj, unweighted=True, indices=centres, directed=False, return_predecessors=True
    )
    rows = labels  # each node is reached only from the centre of its own component
    cols = np.arange(n)
    d = dist[rows, cols].astype(np.int64)
    p = pred[rows, cols].astype(np.int64)
    keep_mask = d % 2 == 0
    kept = np.flatnonzero(keep_mask)
    local = np.full(n, -1, dtype=np.int64)
    local[kept] = np.arange(kept.size)
    anchor = np.where(keep_mask, np.arange(n), p)  # odd-distance nodes: BFS parent (even distance)
    parent = local[anchor]
    if rule == "cluster":
        return kept, _quotient_edges(adj, parent, kept.size), parent
    two_hop = (adj + adj @ adj)[kept][:, kept].tocoo()
    mask = two_hop.row != two_hop.col
    coarse_edges = np.stack([two_hop.row[mask], two_hop.col[mask]]).astype(np.int64)
    return kept, coarse_edges, parent


_CACHE: dict[tuple[str, int, int, str, str], list[HierarchyLevel]] = {}


def anchor_hierarchy(
    edges: np.ndarray, num_nodes: int, levels: int = 3, rule: str = "cluster", anchors: str = "mis"
) -> list[HierarchyLevel]:
    """The anchor hierarchy of a mesh graph, computed once per topology and cached.

    Args:
        edges: (2, E) int mesh edges of the fine level (e.g. :func:`mesh_edges`), indices < ``num_nodes``.
        num_nodes: number of fine nodes V.
        levels: number of coarse levels to build (HOOD: 3).
        rule: coarse connectivity, ``"cluster"`` (default) or ``"two_hop"`` (HOOD; module docstring).
        anchors: anchor choice, ``"mis"`` (default, ~1/4 of the nodes per level) or ``"bfs_even"`` (HOOD,
            ~1/2).

    Returns:
        ``levels`` :class:`HierarchyLevel` objects, coarse level 1 first. A level stops shrinking once every
        component is a single node; levels are still returned (identical node sets) so the schedule stays
        valid.
    """
    edges = np.ascontiguousarray(np.asarray(edges, dtype=np.int64))
    check_rules(rule, anchors)
    key = (hashlib.sha1(edges.tobytes()).hexdigest(), int(num_nodes), int(levels), str(rule), str(anchors))
    if key in _CACHE:
        return _CACHE[key]
    out: list[HierarchyLevel] = []
    nodes = np.arange(num_nodes, dtype=np.int64)
    cur_edges = edges
    n = num_nodes
    for _ in range(levels):
        kept, coarse_edges, parent = coarsen(cur_edges, n, rule, anchors)
        nodes = nodes[kept]
        out.append(HierarchyLevel(nodes=nodes, edges=coarse_edges, parent=parent))
        cur_edges, n = coarse_edges, kept.size
    _CACHE[key] = out
    return out


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique mesh edges of a triangle mesh, both directions.

    Args:
        faces: (F, 3) int vertex indices.

    Returns:
        (2, 2 * E_unique) int64, the first half (i < j) followed by the reversed half.
    """
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=0)
    e = np.sort(e, axis=1)
    e = np.unique(e, axis=0)
    return np.concatenate([e.T, e.T[::-1]], axis=1)


def finest_level_of(levels: list[HierarchyLevel], num_nodes: int) -> np.ndarray:
    """Coarsest hierarchy level each fine node belongs to (0 = fine only, ..., len(levels)).

    Returns:
        (V,) int64.
    """
    depth = np.zeros(num_nodes, dtype=np.int64)
    for k, lvl in enumerate(levels, start=1):
        depth[lvl.nodes] = k
    return depth
