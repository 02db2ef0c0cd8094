"""Rest-state quantities of a :class:`~smln.cloth.Cloth`, computed once, shared by the losses and metrics."""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import cached_property
from typing import NamedTuple

import numpy as np
import torch

from smln.cloth import Cloth, Material
from smln.geometry import dihedral_angles, interior_edges, unique_edges


def _rest_frames_inverse(x: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Dm^-1 of each rest triangle in its own orthonormal 2-D frame, and the rest areas.

    Frame: u = e1 / |e1|, v = n x u with e1 = X1 - X0, e2 = X2 - X0, n the unit normal. Then
    Dm = [[|e1|, e2.u], [0, e2.v]] (columns = edges in 2-D) and
    Dm^-1 = [[1/|e1|, -e2.u/(|e1| e2.v)], [0, 1/e2.v]].

    Returns:
        dm_inv: (F, 2, 2); area: (F,) m^2.
    """
    x = x.double()
    e1 = x[faces[:, 1]] - x[faces[:, 0]]
    e2 = x[faces[:, 2]] - x[faces[:, 0]]
    l1 = torch.linalg.norm(e1, dim=-1)
    u = e1 / l1[:, None]
    n = torch.linalg.cross(e1, e2, dim=-1)
    area = 0.5 * torch.linalg.norm(n, dim=-1)
    n = n / (2 * area[:, None])
    v = torch.linalg.cross(n, u, dim=-1)
    a, b, d = l1, (e2 * u).sum(-1), (e2 * v).sum(-1)
    dm_inv = torch.zeros(faces.shape[0], 2, 2, dtype=x.dtype)
    dm_inv[:, 0, 0] = 1.0 / a
    dm_inv[:, 0, 1] = -b / (a * d)
    dm_inv[:, 1, 1] = 1.0 / d
    return dm_inv.float(), area.float()


class NumpyTopology(NamedTuple):
    """Coordinate-major numpy copies of the index arrays the metrics read every frame (made once per ClothRest).

    Attributes:
        faces: (3, F) int64; edges: (2, E) int64; hinge_faces: (2, H) int64; rest_length: (E,) float32, m.
    """

    faces: np.ndarray
    edges: np.ndarray
    hinge_faces: np.ndarray
    rest_length: np.ndarray


@dataclass
class ClothRest:
    """Everything rest-dependent that the losses and metrics need (build with :meth:`from_cloth`).

    Attributes:
        faces: (F, 3) int64.
        dm_inv: (F, 2, 2) float32, inverse rest edge matrices in each triangle's own 2-D frame, 1/m.
        rest_area: (F,) float32, m^2.
        edges: (E, 2) int64 unique undirected edges; rest_length: (E,) float32, m.
        hinges: (H, 2) int64 interior-edge vertices (a, b); hinge_opposite: (H, 2) int64 opposite vertices;
        hinge_faces: (H, 2) int64 the two faces; rest_angle: (H,) float32 rest dihedral angles, rad;
        bend_coeff: (H,) float32, k_b * l_e^2 / (4 (A1 + A2)) with rest length and areas, J/rad^2.
        layer_index: (V,) int64; layer_slices: contiguous vertex range per layer, inner -> outer.
        mass: (V,) float32 kg; pinned: (V,) bool; free: (V,) float32, 1 for simulated vertices, 0 for pinned.
        material: fabric constants.
    """

    faces: torch.Tensor
    dm_inv: torch.Tensor
    rest_area: torch.Tensor
    edges: torch.Tensor
    rest_length: torch.Tensor
    hinges: torch.Tensor
    hinge_opposite: torch.Tensor
    hinge_faces: torch.Tensor
    rest_angle: torch.Tensor
    bend_coeff: torch.Tensor
    layer_index: torch.Tensor
    layer_slices: list[slice]
    mass: torch.Tensor
    pinned: torch.Tensor
    free: torch.Tensor
    material: Material

    @cached_property
    def numpy_topology(self) -> NumpyTopology:
        """:class:`NumpyTopology` of this cloth (cached)."""

        def cm(a: torch.Tensor) -> np.ndarray:
            return np.ascontiguousarray(a.detach().cpu().numpy().T)

        return NumpyTopology(
            faces=cm(self.faces),
            edges=cm(self.edges),
            hinge_faces=cm(self.hinge_faces),
            rest_length=np.ascontiguousarray(self.rest_length.detach().cpu().numpy(), dtype=np.float32),
        )

    @property
    def num_layers(self) -> int:
        return len(self.layer_slices)

    @classmethod
    def from_cloth(cls, cloth: Cloth, flat_rest_bending: bool = False) -> ClothRest:
        """Precompute rest quantities from ``cloth.rest_vertices``.

        Args:
            cloth: the flat multi-layer cloth.
            flat_rest_bending: if True the rest dihedral angles are 0 (flat sewing panels, HOOD's choice for
                its garments); by default they are the rest mesh's own angles, so the T-pose shape is the
                bending rest state.
        """
        x = cloth.rest_vertices.float()
        faces = cloth.faces.long()
        dm_inv, area = _rest_frames_inverse(x, faces)
        edges = unique_edges(faces)
        rest_length = torch.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], dim=-1)
        ie = interior_edges(faces)
        hl = torch.linalg.norm(x[ie.edges[:, 1]] - x[ie.edges[:, 0]], dim=-1)
        a_sum = area[ie.face_pairs].sum(-1)
        k_b = cloth.material.bending_stiffness
        bend_coeff = k_b * hl**2 / (4.0 * a_sum)
        if flat_rest_bending:
            rest_angle = torch.zeros(len(hl), device=x.device)
        else:
            rest_angle = dihedral_angles(x.double(), ie.edges, ie.opposite).float()
        pinned = cloth.pinned.bool()
        return cls(
            faces=faces,
            dm_inv=dm_inv,
            rest_area=area,
            edges=edges,
            rest_length=rest_length,
            hinges=ie.edges,
            hinge_opposite=ie.opposite,
            hinge_faces=ie.face_pairs,
            rest_angle=rest_angle,
            bend_coeff=bend_coeff.float(),
            layer_index=cloth.layer_index.long(),
            layer_slices=cloth.layer_slices(),
            mass=cloth.vertex_mass.float(),
            pinned=pinned,
            free=(~pinned).float(),
            material=cloth.material,
        )

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> ClothRest:
        """A copy with every tensor on ``device`` and every floating tensor in ``dtype`` (e.g. float64 for
        gradcheck)."""
        kw = {}
        for k in (f.name for f in fields(self)):  # not __dict__: it also holds cached properties
            v = getattr(self, k)
            if isinstance(v, torch.Tensor):
                v = v.to(device=device, dtype=dtype if dtype is not None and v.is_floating_point() else None)
            kw[k] = v
        return ClothRest(**kw)
