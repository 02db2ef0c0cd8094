"""Anchor hierarchy of a garment mesh for down/up-sampling in the processor (paper §3.2, HOOD's scheme).

Per connected component: breadth-first search from a central node, keep the nodes at even BFS distance,
connect kept nodes that are at most two hops apart (``A + A^2`` restricted to the kept nodes). Repeat on the
coarse graph for ``levels`` levels. Every dropped node (odd distance) is assigned to its BFS parent, which
is kept (distance one less, even), so pooling and unpooling never need a search.

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


def coarsen(edges: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One coarsening step of a graph.

    Args:
        edges: (2, E) int edge list over ``n`` nodes (any direction, duplicates allowed).
        n: number of nodes.

    Returns:
        kept: (N_c,) int64 local indices of the kept nodes (even BFS distance from the component centre).
        coarse_edges: (2, E_c) int64 edges between kept nodes at most two hops apart, indices into ``kept``,
            both directions, no self loops.
        parent: (n,) int64 index into ``kept`` of each node's anchor (itself if kept, else its BFS parent).
    """
    adj = _adjacency(edges, n)
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
    two_hop = (adj + adj @ adj)[kept][:, kept].tocoo()
    mask = two_hop.row != two_hop.col
    coarse_edges = np.stack([two_hop.row[mask], two_hop.col[mask]]).astype(np.int64)
    return kept, coarse_edges, parent


_CACHE: dict[tuple[str, int, int], list[HierarchyLevel]] = {}


def anchor_hierarchy(edges: np.ndarray, num_nodes: int, levels: int = 3) -> list[HierarchyLevel]:
    """The anchor hierarchy of a mesh graph, computed once per topology and cached.

    Args:
        edges: (2, E) int mesh edges of the fine level (e.g. :func:`mesh_edges`), indices < ``num_nodes``.
        num_nodes: number of fine nodes V.
        levels: number of coarse levels to build (HOOD: 3).

    Returns:
        ``levels`` :class:`HierarchyLevel` objects, coarse level 1 first. A level stops shrinking once every
        component is a single node; levels are still returned (identical node sets) so the schedule stays
        valid.
    """
    edges = np.ascontiguousarray(np.asarray(edges, dtype=np.int64))
    key = (hashlib.sha1(edges.tobytes()).hexdigest(), int(num_nodes), int(levels))
    if key in _CACHE:
        return _CACHE[key]
    out: list[HierarchyLevel] = []
    nodes = np.arange(num_nodes, dtype=np.int64)
    cur_edges = edges
    n = num_nodes
    for _ in range(levels):
        kept, coarse_edges, parent = coarsen(cur_edges, n)
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
