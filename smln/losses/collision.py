"""Cloth-body collision penalty (HOOD's cubic form; the paper relies on it through HOOD, Eq. 17 omits it)."""

from __future__ import annotations

import torch

from smln.geometry import PointTree, signed_distance_along_normals
from smln.losses.rest import ClothRest

COLLISION_EPS = 3e-3
"""Target clearance from the body, meters (HOOD/ContourCraft use 3-4 mm)."""


def collision_energy(
    x: torch.Tensor,
    body: torch.Tensor,
    body_normals: torch.Tensor,
    rest: ClothRest,
    idx: torch.Tensor | None = None,
    tree: PointTree | None = None,
    eps: float = COLLISION_EPS,
) -> torch.Tensor:
    """E = sum_i max(eps - d_i, 0)^3 over free cloth vertices, unweighted (weight in ``LossWeights``).

    d_i = (x_i - b_j) . n_j is the signed distance of cloth vertex i to its nearest body vertex j along
    that vertex's normal (negative inside the body). The nearest indices come from a KD-tree without
    gradient (pass ``idx`` or a ``tree`` over ``body`` to reuse one); d is differentiable in ``x``.
    Units: m^3; :class:`~smln.losses.total.LossWeights` multiplies it by 1e4 J/m^3 (see there).

    Args:
        x: (V, 3) cloth positions at t+1, meters.
        body: (Vb, 3) body vertices at t+1; body_normals: (Vb, 3) their unit outward normals.
        rest: free mask (pinned vertices are skinned: no penalty).
        idx: (V,) nearest body vertex per cloth vertex, optional.
        tree: KD-tree over ``body``, optional.
        eps: clearance, meters.

    Returns:
        scalar penalty, m^3.
    """
    _, d = signed_distance_along_normals(x, body, body_normals, idx=idx, tree=tree)
    pen = torch.clamp(eps - d, min=0.0)
    return (rest.free * pen * pen * pen).sum()
