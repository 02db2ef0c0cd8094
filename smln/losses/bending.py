"""Bending energy on dihedral angles of interior edges (paper Eq. 20, in HOOD's discrete-shell form)."""

from __future__ import annotations

import math

import torch

from smln.geometry import coordinate_major, dihedral_angles_cm
from smln.losses.rest import ClothRest


def bending_energy(x: torch.Tensor, rest: ClothRest) -> torch.Tensor:
    """Discrete-shell bending energy.

        E = sum_e k_b * l_e^2 / (4 (A_1 + A_2)) * (theta_e - theta_e^rest)^2 / 2

    over interior edges e with rest length l_e, rest areas A_1, A_2 of the two adjacent triangles, bending
    stiffness k_b (``rest.material.bending_stiffness``) and signed dihedral angle theta_e (0 = flat; see
    :func:`smln.geometry.dihedral_angles`); the angle difference is wrapped to [-pi, pi).

    Why not the paper's Eq. 20 (sum of squared Laplacians of face normals): that form has no rest state, so it
    would penalise the curvature the garment has in its own T-pose rest shape, its scale changes with mesh
    resolution, and it has no physical stiffness; the dihedral form is HOOD's (the self-supervised system
    the paper builds on), is resolution-consistent through l^2 / (A_1 + A_2), and uses the material's k_b.

    Args:
        x: (V, 3) positions, meters; leading batch dims allowed.
        rest: precomputed rest state (``bend_coeff`` = k_b l^2 / (4 (A_1 + A_2)), ``rest_angle``).

    Returns:
        scalar energy, J.
    """
    theta = dihedral_angles_cm(coordinate_major(x), rest.hinges, rest.hinge_opposite)
    diff = torch.remainder(theta - rest.rest_angle + math.pi, 2.0 * math.pi) - math.pi
    return 0.5 * (rest.bend_coeff * diff * diff).sum()
