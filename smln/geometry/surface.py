"""Closest points on a triangle surface (libigl's AABB query through gpytoolbox), for the point-to-triangle metrics
(:func:`smln.metrics.behind_surface`) and the repulsion layer's surface reading (:class:`smln.model.SMLN` with
``repulsion_pairing="deeper"``). numpy, no gradient: a closest point is found once and then carried by its
barycentric coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def boundary_edge_keys(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """Sorted int64 keys ``min * V + max`` of the edges used by exactly one face (the open boundary: hems).

    Args:
        faces: (F, 3) int64 vertex indices. num_vertices: V, the rows ``faces`` indexes.
    """
    e = np.sort(np.asarray(faces)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1).astype(np.int64)
    keys, counts = np.unique(e[:, 0] * num_vertices + e[:, 1], return_counts=True)
    return keys[counts == 1]


@dataclass(frozen=True)
class SurfacePoints:
    """Closest surface points of Q queries.

    Attributes:
        corners: (Q, 3) int64 vertex rows of the triangle holding each closest point.
        bary: (Q, 3) float64 barycentric weights of the closest point on those corners (sum 1).
        on_boundary: (Q,) bool, the closest point is on the surface's open boundary (an edge used by one face,
            or a vertex of such an edge): the query lies beyond the surface's edge, not in front of or behind it.
        valid: (Q,) bool, a closest point was found: False for a query that is not finite or whose closest
            triangle is degenerate (zero area: its weights are undefined); such rows hold weights (1, 0, 0).
    """

    corners: np.ndarray
    bary: np.ndarray
    on_boundary: np.ndarray
    valid: np.ndarray


def closest_surface_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                           boundary: np.ndarray | None = None, tol: float = 1e-6) -> SurfacePoints:
    """The closest point of each query on a triangle mesh.

    Args:
        points: (Q, 3) queries, m. vertices: (Nv, 3) m. faces: (F, 3) int64 into ``vertices`` (F >= 1).
        boundary: :func:`boundary_edge_keys` of ``faces`` (None: computed here; pass it when the same faces are
            queried every frame).
        tol: barycentric weights below this count as zero (a closest point on an edge or at a vertex).

    Returns:
        :class:`SurfacePoints`.
    """
    import gpytoolbox

    faces = np.ascontiguousarray(faces, dtype=np.int64)
    nv = len(vertices)
    if len(points) == 0:
        return SurfacePoints(np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, bool))
    points = np.ascontiguousarray(points, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):  # degenerate triangles: NaN weights, marked invalid below
        sq, tri, bary = gpytoolbox.squared_distance(points, np.ascontiguousarray(vertices, np.float64), faces,
                                                    use_cpp=True)
    corners = faces[np.asarray(tri, dtype=np.int64).reshape(-1)]
    bary = np.asarray(bary, dtype=np.float64).reshape(-1, 3).copy()
    valid = np.isfinite(bary).all(axis=1) & np.isfinite(np.asarray(sq)).reshape(-1) & np.isfinite(points).all(axis=1)
    bary[~valid] = (1.0, 0.0, 0.0)
    if boundary is None:
        boundary = boundary_edge_keys(faces, nv)
    on_boundary = np.zeros(len(points), dtype=bool)
    if len(boundary) == 0:
        return SurfacePoints(corners, bary, on_boundary, valid)
    zero = bary < tol
    nzero = zero.sum(axis=1)
    edge_rows = np.flatnonzero(nzero == 1)  # on the edge opposite the zero corner
    if len(edge_rows):
        k = np.argmax(zero[edge_rows], axis=1)
        a = corners[edge_rows, (k + 1) % 3]
        b = corners[edge_rows, (k + 2) % 3]
        on_boundary[edge_rows] = np.isin(np.minimum(a, b) * nv + np.maximum(a, b), boundary)
    vert_rows = np.flatnonzero(nzero >= 2)  # at the corner with the largest weight
    if len(vert_rows):
        corner = corners[vert_rows, np.argmax(bary[vert_rows], axis=1)]
        on_boundary[vert_rows] = np.isin(corner, np.unique(np.stack([boundary // nv, boundary % nv])))
    return SurfacePoints(corners, bary, on_boundary & valid, valid)
