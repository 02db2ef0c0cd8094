"""Inertia term of the implicit-Euler incremental potential (not in the paper's Eq. 17; HOOD/SNUG have it)."""

from __future__ import annotations

import torch

from smln.losses.rest import ClothRest


def inertia_energy(
    x_prev: torch.Tensor, x_cur: torch.Tensor, x_next: torch.Tensor, rest: ClothRest, dt: float
) -> torch.Tensor:
    """E = sum_i m_i ||x_{t+1} - (x_t + v_t)||^2 / (2 dt^2), v_t = x_t - x_{t-1} (per-frame velocity).

    The paper's Eq. 17 omits this term, but without it the minimiser of the remaining (static) energies is a
    quasi-static pose: there is no momentum, no swinging, no dynamics at all. It is the kinetic part of the
    incremental potential whose minimiser is one implicit-Euler step (SNUG, HOOD): kept, with weight 1.
    Zero for constant velocity. Pinned vertices are left out (they follow the skinning).

    Args:
        x_prev, x_cur, x_next: (V, 3) positions at t-1, t, t+1, meters.
        rest: masses (kg) and the free mask.
        dt: time step, seconds.

    Returns:
        scalar energy, J.
    """
    a = x_next - 2.0 * x_cur + x_prev
    return (rest.mass * rest.free * (a * a).sum(-1)).sum() / (2.0 * dt * dt)
