"""Gravitational potential energy (paper Eq. 21)."""

from __future__ import annotations

import torch

from smln.cloth import GRAVITY
from smln.losses.rest import ClothRest


def gravity_energy(x: torch.Tensor, rest: ClothRest, g: float = GRAVITY) -> torch.Tensor:
    """E = sum_i m_i g z_i over free (non-pinned) vertices (Eq. 21, lambda = g m).

    Pinned vertices follow the skinning; they would only add a constant, so they are left out.

    Args:
        x: (V, 3) positions, meters (Z up); leading batch dims allowed.
        rest: masses (kg) and the free mask.
        g: gravitational acceleration, m/s^2.

    Returns:
        scalar energy, J (relative to z = 0, the floor).
    """
    return g * (rest.mass * rest.free * x[..., 2]).sum()
