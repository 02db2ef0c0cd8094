"""The :class:`Garment`: one cloth layer's rest mesh in the body's canonical T-pose and its simulation data."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from smln.cloth import Material
from smln.garments.meshops import boundary_loops, vertex_areas


class GarmentError(ValueError):
    """A garment (or a user's garment file) is unusable; the message says why in one line."""


def vertex_mass(vertices: np.ndarray, faces: np.ndarray, density: float) -> np.ndarray:
    """Paper Eq. 3: m_i = rho * sum of the adjacent triangle areas / 3.

    Args:
        vertices: (V, 3) m; faces: (F, 3); density: kg/m^2.

    Returns:
        (V,) float32 masses, kg; they sum to density * total area.
    """
    return (density * vertex_areas(np.asarray(vertices, np.float64), faces)).astype(np.float32)


@dataclass
class Garment:
    """One garment layer.

    Attributes:
        name: instance name (e.g. ``"tshirt"``); garment_type: generator type or ``"user"``.
        vertices: (V, 3) float32 rest positions in the body's canonical T-pose, meters.
        faces: (F, 3) int64, outward-facing triangles.
        vertex_mass: (V,) float32 kg (Eq. 3).
        pinned: (V,) bool, vertices that follow the skinning (waistbands).
        skin_indices: (V, 7) int64 body bone indices; skin_weights: (V, 7) float32, rows sum to 1.
        material: fabric constants.
        shape: body shape preset the garment was built on.
        edge_length: target edge length, m.
        note: how a user's mesh was read when it was not in the body's frame and meters (``"read in cm, turned
            from Y up to Z up"``), else empty.
    """

    name: str
    garment_type: str
    vertices: np.ndarray
    faces: np.ndarray
    vertex_mass: np.ndarray
    pinned: np.ndarray
    skin_indices: np.ndarray
    skin_weights: np.ndarray
    material: Material = field(default_factory=Material)
    shape: str = ""
    edge_length: float = 0.0
    note: str = ""

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def boundary_loops(self) -> list[np.ndarray]:
        """Open boundary loops as ordered vertex index arrays."""
        return boundary_loops(self.faces)

    def area(self) -> float:
        """Total surface area, m^2."""
        v = self.vertices.astype(np.float64)
        c = np.cross(v[self.faces[:, 1]] - v[self.faces[:, 0]], v[self.faces[:, 2]] - v[self.faces[:, 0]])
        return float(0.5 * np.linalg.norm(c, axis=1).sum())

    def with_vertices(self, vertices: np.ndarray) -> Garment:
        """A copy with new rest vertices (mass recomputed; weights, pins and faces kept)."""
        v = np.asarray(vertices, dtype=np.float32)
        return Garment(self.name, self.garment_type, v, self.faces.copy(),
                       vertex_mass(v, self.faces, self.material.density), self.pinned.copy(),
                       self.skin_indices.copy(), self.skin_weights.copy(), self.material, self.shape,
                       self.edge_length)

    def save(self, path: Path) -> None:
        """Write a compressed npz (arrays plus the material constants)."""
        mat = self.material
        np.savez_compressed(
            path, name=self.name, garment_type=self.garment_type, vertices=self.vertices, faces=self.faces,
            vertex_mass=self.vertex_mass, pinned=self.pinned, skin_indices=self.skin_indices,
            skin_weights=self.skin_weights, shape=self.shape, edge_length=self.edge_length,
            material=np.array([getattr(mat, f.name) for f in fields(Material)], dtype=np.float64),
        )

    @classmethod
    def load(cls, path: Path) -> Garment:
        """Read a file written by :meth:`save`."""
        d = np.load(path, allow_pickle=False)
        mat = Material(**{f.name: float(x) for f, x in zip(fields(Material), d["material"], strict=True)})
        return cls(str(d["name"]), str(d["garment_type"]), d["vertices"], d["faces"].astype(np.int64),
                   d["vertex_mass"], d["pinned"].astype(bool), d["skin_indices"].astype(np.int64),
                   d["skin_weights"], mat, str(d["shape"]), float(d["edge_length"]))

    @classmethod
    def from_obj(cls, path: str | Path, body=None, **kwargs) -> Garment:
        """Load a user's garment mesh (see :func:`smln.garments.obj_import.garment_from_obj`)."""
        from smln.garments.obj_import import garment_from_obj

        return garment_from_obj(path, body, **kwargs)
