"""Mesh helpers and proximity queries shared by losses, metrics, the graph builder and the repulsion layer.

Mesh (torch, differentiable, batched over leading dims): :func:`face_normals`, :func:`face_areas`,
:func:`vertex_normals`, :func:`unique_edges`, :func:`interior_edges`, :func:`hinge_normals`,
:func:`dihedral_angles`, :func:`vertex_neighbors`.

Proximity (scipy cKDTree; indices without gradient, distances differentiable): :func:`build_tree`,
:func:`nearest_vertices`, :func:`signed_distance_along_normals`, :func:`close_pairs`.
"""

from smln.geometry.mesh import (
    InteriorEdges,
    dihedral_angles,
    face_areas,
    face_normals,
    hinge_normals,
    interior_edges,
    unique_edges,
    vertex_neighbors,
    vertex_normals,
)
from smln.geometry.proximity import (
    build_tree,
    close_pairs,
    nearest_vertices,
    signed_distance_along_normals,
)

__all__ = [
    "InteriorEdges",
    "build_tree",
    "close_pairs",
    "dihedral_angles",
    "face_areas",
    "face_normals",
    "hinge_normals",
    "interior_edges",
    "nearest_vertices",
    "signed_distance_along_normals",
    "unique_edges",
    "vertex_neighbors",
    "vertex_normals",
]
