"""Triangle-mesh helpers: normals, areas, edges and edge-adjacent face pairs.

All functions are vectorised torch code (no Python loops over faces or edges) and differentiable in the
positions ``x``. Positions may carry leading batch dimensions: ``x`` is ``(..., V, 3)``, float, meters;
``faces`` is ``(F, 3)`` int64 and shared by the batch.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

_EPS = 1e-12


# Coordinate-major ("structure of arrays") helpers. The differentiable mesh quantities below are computed on
# (3, ..., N) tensors: gathers are ``index_select`` along the last axis (whose backward is one index_add, not
# an accumulating index_put), and cross/dot products are elementwise on contiguous rows instead of reductions
# over an axis of length 3. On the 2-layer 5,000-vertex benchmark cloth this halves the CPU time of the loss
# forward + backward against the (V, 3) row form (bench/losses_metrics.py).


def coordinate_major(x: torch.Tensor) -> torch.Tensor:
    """(..., V, 3) -> (3, ..., V) contiguous copy (differentiable)."""
    return x.movedim(-1, 0).contiguous()


def gather_cm(xt: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Columns ``idx`` of a coordinate-major tensor: (3, ..., V), (K,) -> (3, ..., K)."""
    return xt.index_select(-1, idx)


def gather_corners_cm(xt: torch.Tensor, corners: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Positions of the corners of C-tuples (faces: C = 3, hinges: C = 4) in one gather.

    Args:
        xt: (3, ..., V) coordinate-major positions.
        corners: (N, C) int64 vertex indices.

    Returns:
        C tensors (3, ..., N): the k-th holds the k-th corner of every tuple.
    """
    n, c = corners.shape
    g = xt.index_select(-1, corners.t().reshape(-1))  # (3, ..., C * N), corner-major
    return g.split(n, dim=-1) if n else tuple(g for _ in range(c))


def cross_cm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product of coordinate-major vectors: (3, ...), (3, ...) -> (3, ...)."""
    a0, a1, a2 = a.unbind(0)  # unbind, not a[k]: one backward node instead of three zero-filled selects
    b0, b1, b2 = b.unbind(0)
    return torch.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))


def dot_cm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Dot product of coordinate-major vectors: (3, ...), (3, ...) -> (...)."""
    return (a * b).sum(0)


def normalize_cm(v: torch.Tensor) -> torch.Tensor:
    """Unit coordinate-major vectors; zero vectors stay (almost) zero instead of becoming NaN."""
    return v / torch.sqrt(dot_cm(v, v) + _EPS)


def face_cross_cm(xt: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unnormalised face normals (x1 - x0) x (x2 - x0), norm = 2 * area: (3, ..., V), (F, 3) -> (3, ..., F)."""
    x0, x1, x2 = gather_corners_cm(xt, faces)
    return cross_cm(x1 - x0, x2 - x0)


def vertex_normals_cm(xt: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals, coordinate-major: (3, ..., V), (F, 3) -> (3, ..., V).

    The same values as :func:`vertex_normals` (sum of the adjacent faces' cross products, normalised).
    """
    c = face_cross_cm(xt, faces)  # (3, ..., F)
    corners = faces.t().reshape(-1)  # corner k of every face, k = 0, 1, 2
    acc = torch.zeros_like(xt).index_add(-1, corners, torch.cat((c, c, c), dim=-1))
    return normalize_cm(acc)


def _face_cross(x: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unnormalised face normals (x1 - x0) x (x2 - x0); norm = 2 * area. Shape (..., F, 3)."""
    return face_cross_cm(coordinate_major(x), faces).movedim(0, -1)


def _normalize(v: torch.Tensor) -> torch.Tensor:
    """Unit vectors along the last axis; zero vectors stay (almost) zero instead of becoming NaN."""
    return v / torch.sqrt((v * v).sum(-1, keepdim=True) + _EPS)


def face_normals(x: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals, right-handed in the face's vertex order.

    Args:
        x: (..., V, 3) vertex positions, meters.
        faces: (F, 3) int64 vertex indices.

    Returns:
        (..., F, 3) unit normals (degenerate faces give ~0 vectors, never NaN).
    """
    return _normalize(_face_cross(x, faces))


def face_areas(x: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Triangle areas.

    Args:
        x: (..., V, 3) vertex positions, meters.
        faces: (F, 3) int64.

    Returns:
        (..., F) areas, m^2.
    """
    c = _face_cross(x, faces)
    return 0.5 * torch.sqrt((c * c).sum(-1) + _EPS)


def vertex_normals(x: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals (sum of the adjacent faces' area-scaled normals, normalised).

    Args:
        x: (..., V, 3) vertex positions, meters.
        faces: (F, 3) int64.

    Returns:
        (..., V, 3) unit normals; isolated vertices get ~0 vectors.
    """
    return vertex_normals_cm(coordinate_major(x), faces).movedim(0, -1).contiguous()


def unique_edges(faces: torch.Tensor) -> torch.Tensor:
    """Undirected edges of a triangle mesh.

    Args:
        faces: (F, 3) int64.

    Returns:
        (E, 2) int64, each row sorted (i < j), rows sorted lexicographically, no duplicates.
    """
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], dim=0)
    e = torch.sort(e, dim=1).values
    return torch.unique(e, dim=0)


class InteriorEdges(NamedTuple):
    """Edges shared by exactly two faces (the hinges of dihedral bending).

    Attributes:
        edges: (E, 2) int64 hinge vertices (a, b), in the order they appear in ``faces[face_pairs[:, 0]]``.
        opposite: (E, 2) int64, the vertex of each of the two faces that is not on the hinge (c1, c2).
        face_pairs: (E, 2) int64 indices of the two faces.
    """

    edges: torch.Tensor
    opposite: torch.Tensor
    face_pairs: torch.Tensor


def interior_edges(faces: torch.Tensor) -> InteriorEdges:
    """Find every edge shared by exactly two faces, with the two opposite vertices.

    Boundary edges (one face) and non-manifold edges (three or more faces) are left out.

    Args:
        faces: (F, 3) int64.

    Returns:
        :class:`InteriorEdges` with E rows.
    """
    faces = faces.long()
    nf = faces.shape[0]
    a = torch.cat([faces[:, 0], faces[:, 1], faces[:, 2]])
    b = torch.cat([faces[:, 1], faces[:, 2], faces[:, 0]])
    c = torch.cat([faces[:, 2], faces[:, 0], faces[:, 1]])
    fid = torch.arange(nf, device=faces.device).repeat(3)
    n = int(faces.max().item()) + 1 if nf else 0
    key = torch.minimum(a, b) * n + torch.maximum(a, b)
    key, order = torch.sort(key, stable=True)
    m = key.shape[0]
    if m < 2:
        empty = torch.zeros((0, 2), dtype=torch.long, device=faces.device)
        return InteriorEdges(empty, empty.clone(), empty.clone())
    same_next = key[:-1] == key[1:]  # (m-1,)
    first = torch.zeros(m, dtype=torch.bool, device=faces.device)
    first[:-1] = same_next
    # exactly two: key[i] == key[i+1], key[i-1] != key[i], key[i+2] != key[i]
    prev_diff = torch.ones(m, dtype=torch.bool, device=faces.device)
    prev_diff[1:] = ~same_next
    next2_diff = torch.ones(m, dtype=torch.bool, device=faces.device)
    next2_diff[:-2] = key[:-2] != key[2:]
    i = torch.nonzero(first & prev_diff & next2_diff).squeeze(1)
    h1, h2 = order[i], order[i + 1]
    return InteriorEdges(
        edges=torch.stack([a[h1], b[h1]], dim=1),
        opposite=torch.stack([c[h1], c[h2]], dim=1),
        face_pairs=torch.stack([fid[h1], fid[h2]], dim=1),
    )


def hinge_normals(
    x: torch.Tensor, edges: torch.Tensor, opposite: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unnormalised normals of the two faces of each hinge, oriented consistently from the 4 vertices alone.

    n1 = (x_b - x_a) x (x_c1 - x_a), n2 = (x_c2 - x_a) x (x_b - x_a): for a flat hinge (c1, c2 on opposite
    sides of the edge) n1 and n2 point the same way, whatever the faces' winding in the mesh.

    Args:
        x: (..., V, 3) positions.
        edges: (E, 2) hinge vertices (a, b); opposite: (E, 2) opposite vertices (c1, c2).

    Returns:
        n1, n2: (..., E, 3) unnormalised (norm = 2 * face area); e: (..., E, 3) edge vector x_b - x_a.
    """
    n1, n2, e = hinge_normals_cm(coordinate_major(x), edges, opposite)
    return n1.movedim(0, -1), n2.movedim(0, -1), e.movedim(0, -1)


def hinge_normals_cm(
    xt: torch.Tensor, edges: torch.Tensor, opposite: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`hinge_normals` on coordinate-major positions (3, ..., V); returns (3, ..., E) each."""
    xa, xb, c1, c2 = gather_corners_cm(xt, torch.cat((edges, opposite), dim=1))
    e = xb - xa
    return cross_cm(e, c1 - xa), cross_cm(c2 - xa, e), e


def dihedral_angles(x: torch.Tensor, edges: torch.Tensor, opposite: torch.Tensor) -> torch.Tensor:
    """Signed bending angle of each hinge (0 = flat), radians in (-pi, pi].

    theta = atan2((n1 x n2) . e_hat, n1 . n2) with the hinge normals of :func:`hinge_normals`.

    Args:
        x: (..., V, 3) positions; edges, opposite: (E, 2) int64 from :func:`interior_edges`.

    Returns:
        (..., E) angles.
    """
    return dihedral_angles_cm(coordinate_major(x), edges, opposite)


def dihedral_angles_cm(xt: torch.Tensor, edges: torch.Tensor, opposite: torch.Tensor) -> torch.Tensor:
    """:func:`dihedral_angles` on coordinate-major positions (3, ..., V); returns (..., E)."""
    n1, n2, e = hinge_normals_cm(xt, edges, opposite)
    n1, n2, e = normalize_cm(n1), normalize_cm(n2), normalize_cm(e)
    return torch.atan2(dot_cm(cross_cm(n1, n2), e), dot_cm(n1, n2))


def vertex_neighbors(faces: torch.Tensor, num_vertices: int | None = None) -> torch.Tensor:
    """One-ring neighbour table of a mesh, padded.

    Args:
        faces: (F, 3) int64.
        num_vertices: V (default: max index + 1).

    Returns:
        (V, K) int64, K = max valence; row i lists i's neighbours, padded with i itself.
    """
    n = int(num_vertices if num_vertices is not None else faces.max().item() + 1)
    e = unique_edges(faces)
    src = torch.cat([e[:, 0], e[:, 1]])
    dst = torch.cat([e[:, 1], e[:, 0]])
    order = torch.argsort(src, stable=True)
    src, dst = src[order], dst[order]
    deg = torch.bincount(src, minlength=n)
    start = torch.cumsum(deg, 0) - deg
    rank = torch.arange(len(src)) - start[src]
    k = int(deg.max().item()) if len(src) else 1
    table = torch.arange(n).unsqueeze(1).repeat(1, k)
    table[src, rank] = dst
    return table
