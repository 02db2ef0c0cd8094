"""Mesh helpers and proximity queries shared by losses, metrics, the graph builder and the repulsion layer.

Mesh (torch, differentiable, batched over leading dims): :func:`face_normals`, :func:`face_areas`,
:func:`vertex_normals`, :func:`unique_edges`, :func:`interior_edges`, :func:`hinge_normals`,
:func:`dihedral_angles`, :func:`vertex_neighbors`.

Proximity (pykdtree via :class:`PointTree`; indices without gradient, distances differentiable): :func:`build_tree`,
:func:`nearest_vertices`, :func:`signed_distance_along_normals`, :func:`close_pairs`; :func:`set_threads`.
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
    PointTree,
    build_tree,
    close_pairs,
    nearest_vertices,
    set_threads,
    signed_distance_along_normals,
)

__all__ = [
    "InteriorEdges",
    "PointTree",
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
