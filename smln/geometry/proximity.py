"""Proximity queries between point sets (cloth layers, body) built on ``scipy.spatial.cKDTree``.

Index searches run on the CPU in numpy and carry no gradient; distances that depend on positions are then
recomputed in torch from the indices so that they stay differentiable. Inputs may be torch tensors (any
device) or numpy arrays; outputs are torch tensors on the query's device (CPU for numpy queries).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

ArrayLike = torch.Tensor | np.ndarray


def _np(x: ArrayLike) -> np.ndarray:
    """(N, 3) float array on the CPU, detached."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(x)


def _device(x: ArrayLike) -> torch.device:
    return x.device if isinstance(x, torch.Tensor) else torch.device("cpu")


def _torch(x: ArrayLike, device: torch.device) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.as_tensor(x, device=device)


def build_tree(points: ArrayLike) -> cKDTree:
    """A KD-tree over ``points`` (N, 3), meters; reuse it for every query against the same positions.

    Built unbalanced without compacting (about twice as fast to build; queries cost the same).
    """
    return cKDTree(_np(points), balanced_tree=False, compact_nodes=False)


def nearest_vertices(
    query: ArrayLike, ref: ArrayLike | None = None, tree: cKDTree | None = None, workers: int = 1
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest reference vertex of each query point (Euclidean).

    Args:
        query: (N, 3) points, meters.
        ref: (M, 3) reference vertices; may be None when ``tree`` is given.
        tree: a prebuilt :func:`build_tree` over ``ref`` (skips the build).
        workers: threads for the query (scipy's ``workers``; -1 = all cores).

    Returns:
        idx: (N,) int64 index into ``ref``; dist: (N,) float32 distance, meters (no gradient).
        Both on the query's device.
    """
    if tree is None:
        if ref is None:
            raise ValueError("nearest_vertices needs ref or tree")
        tree = build_tree(ref)
    dist, idx = tree.query(_np(query), k=1, workers=workers)
    dev = _device(query)
    return (
        torch.from_numpy(np.asarray(idx, dtype=np.int64)).to(dev),
        torch.from_numpy(np.asarray(dist, dtype=np.float32)).to(dev),
    )


def signed_distance_along_normals(
    query: ArrayLike,
    ref: ArrayLike,
    ref_normals: ArrayLike,
    idx: torch.Tensor | None = None,
    tree: cKDTree | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance of each query point to its nearest reference vertex, along that vertex's normal.

    d_i = (x_i - r_j) . n_j with j = idx_i the nearest reference vertex. Negative = behind the reference
    surface (inside the body / under the inner layer). Differentiable in ``query``, ``ref`` and
    ``ref_normals`` when they are torch tensors; the indices themselves carry no gradient.

    Args:
        query: (N, 3) points, meters.
        ref: (M, 3) reference vertices, meters.
        ref_normals: (M, 3) unit normals of the reference vertices (outward).
        idx: (N,) int64 precomputed nearest indices (e.g. from an earlier time step); found if None.
        tree: optional prebuilt tree over ``ref`` (used only when ``idx`` is None).

    Returns:
        idx: (N,) int64; d: (N,) signed distance, meters, dtype of ``query``.
    """
    dev = _device(query)
    if idx is None:
        idx, _ = nearest_vertices(query, ref, tree=tree)
    q = _torch(query, dev)
    r = _torch(ref, dev)
    n = _torch(ref_normals, dev)
    idx = idx.to(r.device)
    d = ((q - r[idx].to(q.device)) * n[idx].to(q.device)).sum(-1)
    return idx.to(dev), d


def close_pairs(
    query: ArrayLike,
    ref: ArrayLike | None = None,
    radius: float = 0.02,
    k: int = 1,
    tree: cKDTree | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pairs (query point, reference vertex) closer than ``radius``: the ``k`` nearest with a distance cut.

    Typical use: cross-layer pairs (outer layer as ``query``, inner layer as ``ref``) for virtual edges,
    the repulsion layer and the repulsion loss.

    Args:
        query: (N, 3) points, meters.
        ref: (M, 3) reference vertices (or None with ``tree``).
        radius: cut-off distance, meters (strict: d < radius).
        k: neighbours per query point considered.
        tree: optional prebuilt tree over ``ref``.

    Returns:
        qi: (P,) int64 query indices; ri: (P,) int64 reference indices; dist: (P,) float32 meters.
        Sorted by query index, then by distance. On the query's device.
    """
    if tree is None:
        if ref is None:
            raise ValueError("close_pairs needs ref or tree")
        tree = build_tree(ref)
    dist, idx = tree.query(_np(query), k=k, distance_upper_bound=radius)
    dist = np.asarray(dist).reshape(len(dist), -1)
    idx = np.asarray(idx).reshape(len(idx), -1)
    keep = np.isfinite(dist)
    qi = np.nonzero(keep)[0]
    dev = _device(query)
    return (
        torch.from_numpy(qi.astype(np.int64)).to(dev),
        torch.from_numpy(idx[keep].astype(np.int64)).to(dev),
        torch.from_numpy(dist[keep].astype(np.float32)).to(dev),
    )
