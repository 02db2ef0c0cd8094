"""smln.graph: the multi-layer garment graph (mesh, virtual inter-layer and body edges) and anchor hierarchy."""

from smln.graph.hierarchy import HierarchyLevel, anchor_hierarchy, mesh_edges
from smln.graph.multilayer import (
    BODY_EDGE_DIM,
    LEGACY_BODY_EDGE_DIM,
    MESH_EDGE_DIM,
    NODE_DIM,
    NODE_FEATURES,
    VIRTUAL_EDGE_DIM,
    GraphInputs,
    GraphTopology,
    vertex_normals,
)

__all__ = [
    "BODY_EDGE_DIM",
    "LEGACY_BODY_EDGE_DIM",
    "MESH_EDGE_DIM",
    "NODE_DIM",
    "NODE_FEATURES",
    "VIRTUAL_EDGE_DIM",
    "GraphInputs",
    "GraphTopology",
    "HierarchyLevel",
    "anchor_hierarchy",
    "mesh_edges",
    "vertex_normals",
]
