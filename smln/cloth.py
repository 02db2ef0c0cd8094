"""The flat, multi-layer view of an outfit that the graph, the losses, the metrics and the rollout share.

An :class:`~smln.garments.Outfit` is an ordered stack of garments (inner -> outer). Everything that steps
or scores the cloth works on one concatenated vertex array instead, described by :class:`Cloth`:
vertices of layer 0 first, then layer 1, ... and faces indexing into that concatenation.

Conventions (see docs/ARCHITECTURE.md): Z up, meters, seconds, float32; layer 0 touches the body.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

GRAVITY = 9.81
"""Gravitational acceleration, m/s^2 (acts along -Z)."""

FPS = 30
DT = 1.0 / FPS
"""Simulation time step, seconds (30 fps)."""


@dataclass(frozen=True)
class Material:
    """Fabric constants (SNUG/HOOD defaults).

    Attributes:
        density: area density rho, kg/m^2.
        lame_mu: first Lame parameter mu, Pa (N/m for the membrane energy with ``thickness``).
        lame_lambda: second Lame parameter lambda, Pa.
        bending_stiffness: k_b, N*m (J).
        thickness: shell thickness h, m, multiplies the membrane energy density.
        friction: Coulomb friction coefficient mu against the body and other layers (paper: 0.5).
    """

    density: float = 0.20022
    lame_mu: float = 23600.0
    lame_lambda: float = 44400.0
    bending_stiffness: float = 3.962e-05
    thickness: float = 4.7e-04
    friction: float = 0.5

    def as_features(self) -> torch.Tensor:
        """Three material features scaled to roughly [0, 1] (HOOD's node/edge material input).

        Returns:
            (3,) float32: log-scaled mu, lambda and bending stiffness.
        """
        import math

        return torch.tensor(
            [
                (math.log10(self.lame_mu) - 3.0) / 3.0,
                (math.log10(self.lame_lambda) - 3.0) / 3.0,
                (math.log10(self.bending_stiffness) + 7.0) / 4.0,
            ],
            dtype=torch.float32,
        )


@dataclass
class Cloth:
    """All garment layers of an outfit, concatenated.

    Attributes:
        rest_vertices: (V, 3) float32, meters. Canonical T-pose rest positions (the rest state of stretch and
            bending).
        faces: (F, 3) int64 indices into the concatenated vertices; every face lies within one layer.
        layer_index: (V,) int64, 0 = innermost layer.
        vertex_mass: (V,) float32, kg (paper Eq. 3: density * adjacent triangle areas / 3).
        pinned: (V,) bool, vertices that follow the skinning instead of the network (waistbands).
        skin_indices: (V, K) int64 body bone indices for linear blend skinning.
        skin_weights: (V, K) float32 bone weights, rows sum to 1.
        material: fabric constants shared by all layers.
        layer_names: one garment name per layer, inner -> outer.
    """

    rest_vertices: torch.Tensor
    faces: torch.Tensor
    layer_index: torch.Tensor
    vertex_mass: torch.Tensor
    pinned: torch.Tensor
    skin_indices: torch.Tensor
    skin_weights: torch.Tensor
    material: Material = field(default_factory=Material)
    layer_names: list[str] = field(default_factory=list)

    @property
    def num_vertices(self) -> int:
        return int(self.rest_vertices.shape[0])

    @property
    def num_layers(self) -> int:
        return int(self.layer_index.max().item()) + 1 if self.layer_index.numel() else 0

    def layer_slices(self) -> list[slice]:
        """Contiguous vertex range of each layer, inner -> outer."""
        counts = torch.bincount(self.layer_index, minlength=self.num_layers).tolist()
        out, start = [], 0
        for c in counts:
            out.append(slice(start, start + c))
            start += c
        return out

    def to(self, device: torch.device | str) -> Cloth:
        """A copy with every tensor on ``device``."""
        return Cloth(
            rest_vertices=self.rest_vertices.to(device),
            faces=self.faces.to(device),
            layer_index=self.layer_index.to(device),
            vertex_mass=self.vertex_mass.to(device),
            pinned=self.pinned.to(device),
            skin_indices=self.skin_indices.to(device),
            skin_weights=self.skin_weights.to(device),
            material=self.material,
            layer_names=list(self.layer_names),
        )
