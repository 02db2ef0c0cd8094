"""Skinning weights for garments, transferred from the body.

Each garment vertex copies the weights of its nearest body vertex. For loose parts (skirts, the skirt of a dress,
jacket tails) copying would make the cloth follow one leg, so their weights are instead diffused over the garment
mesh (HOOD does the same): the weights of the fitted part are kept and the loose part gets the harmonic
interpolation of them (a sparse Laplace solve with the fitted vertices as Dirichlet values).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from smln.garments.meshops import adjacency


def dense_weights(skin_indices: np.ndarray, skin_weights: np.ndarray, num_bones: int) -> np.ndarray:
    """(N, B) dense weights from (N, K) sparse indices/weights."""
    out = np.zeros((len(skin_indices), num_bones))
    np.add.at(out, (np.repeat(np.arange(len(skin_indices)), skin_indices.shape[1]), skin_indices.ravel()),
              skin_weights.ravel())
    return out


def top_k(dense: np.ndarray, k: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Keep the ``k`` largest weights per row, renormalised: (N, k) int64 indices, (N, k) float32 weights."""
    idx = np.argsort(-dense, axis=1)[:, :k]
    w = np.take_along_axis(dense, idx, axis=1)
    w = np.clip(w, 0.0, None)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    return idx.astype(np.int64), w.astype(np.float32)


def transfer_weights(
    vertices: np.ndarray,
    faces: np.ndarray,
    body_vertices: np.ndarray,
    body_skin_indices: np.ndarray,
    body_skin_weights: np.ndarray,
    num_bones: int,
    loose: np.ndarray | None = None,
    k: int = 7,
) -> tuple[np.ndarray, np.ndarray]:
    """Garment skinning weights.

    Args:
        vertices: (V, 3) garment rest vertices (T-pose), m; faces: (F, 3).
        body_vertices: (Vb, 3) body T-pose vertices; body_skin_indices/weights: (Vb, K).
        num_bones: B.
        loose: (V,) bool, vertices whose weights are diffused from the rest of the garment (None: none).
        k: weights kept per vertex.

    Returns:
        (V, k) int64 bone indices and (V, k) float32 weights (rows sum to 1).
    """
    _, j = cKDTree(body_vertices).query(vertices)
    dense = dense_weights(body_skin_indices[j], body_skin_weights[j], num_bones)
    if loose is not None and loose.any() and (~loose).any():
        adj = adjacency(faces, len(vertices))
        lap = sp.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj
        free, fixed = np.flatnonzero(loose), np.flatnonzero(~loose)
        a = lap[free][:, free].tocsc()
        rhs = -(lap[free][:, fixed] @ dense[fixed])
        # components of the loose part not touching the fixed part keep their nearest-vertex weights
        a = a + sp.identity(len(free), format="csc") * 1e-9
        dense[free] = splu(a).solve(np.asarray(rhs) + 1e-9 * dense[free])
    return top_k(dense, k)
