"""Mesh helpers and proximity queries shared by losses, metrics, the graph builder and the repulsion layer.

Mesh (torch, differentiable, batched over leading dims): :func:`face_normals`, :func:`face_areas`,
:func:`vertex_normals`, :func:`unique_edges`, :func:`interior_edges`, :func:`hinge_normals`,
:func:`dihedral_angles`, :func:`vertex_neighbors`; coordinate-major (3, ..., N) variants ``*_cm`` for the hot
paths of the losses.

Proximity (pykdtree via :class:`PointTree`; indices without gradient, distances differentiable): :func:`build_tree`,
:func:`nearest_vertices`, :func:`signed_distance_along_normals`, :func:`close_pairs`; :func:`set_threads`.

Surface (numpy, gpytoolbox's AABB query; :mod:`smln.geometry.surface`): :func:`closest_surface_points` (corners and
barycentric weights of the closest triangle point, and whether it lies on the open boundary),
:func:`boundary_edge_keys`.
"""

from smln.geometry.mesh import (
    InteriorEdges,
    coordinate_major,
    cross_cm,
    dihedral_angles,
    dihedral_angles_cm,
    dot_cm,
    face_areas,
    face_cross_cm,
    face_normals,
    gather_cm,
    gather_corners_cm,
    hinge_normals,
    hinge_normals_cm,
    interior_edges,
    normalize_cm,
    unique_edges,
    vertex_neighbors,
    vertex_normals,
    vertex_normals_cm,
)
from smln.geometry.proximity import (
    PointTree,
    build_tree,
    close_pairs,
    nearest_vertices,
    set_threads,
    signed_distance_along_normals,
)
from smln.geometry.surface import SurfacePoints, boundary_edge_keys, closest_surface_points

__all__ = [
    "coordinate_major",
    "cross_cm",
    "dihedral_angles_cm",
    "dot_cm",
    "face_cross_cm",
    "gather_cm",
    "gather_corners_cm",
    "hinge_normals_cm",
    "normalize_cm",
    "vertex_normals_cm",
    "InteriorEdges",
    "PointTree",
    "SurfacePoints",
    "boundary_edge_keys",
    "closest_surface_points",
    "build_tree",
    "close_pairs",
    "dihedral_angles",
    "face_areas",
    "face_normals",
    "hinge_normals",
    "interior_edges",
    "nearest_vertices",
    "set_threads",
    "signed_distance_along_normals",
    "unique_edges",
    "vertex_neighbors",
    "vertex_normals",
]
