"""Membrane stretching energy: Saint Venant-Kirchhoff with the Green strain (paper Eq. 18-19, HOOD's form)."""

from __future__ import annotations

import torch

from smln.geometry import coordinate_major, dot_cm, gather_corners_cm
from smln.losses.rest import ClothRest


def stretch_energy(x: torch.Tensor, rest: ClothRest) -> torch.Tensor:
    """StVK membrane energy of the whole cloth.

    Per triangle f: D_s = [x1 - x0, x2 - x0] (3x2), F = D_s D_m^-1 (3x2) with D_m in the rest triangle's own
    2-D frame, Green strain G = 1/2 (F^T F - I) (2x2), second Piola-Kirchhoff stress
    S = mu G + 1/2 lambda tr(G) I,
    energy density tr(S^T G) (Eq. 18) = mu tr(G^2) + 1/2 lambda tr(G)^2 (G symmetric), and

        E = sum_f A_f * h * tr(S^T G)            (Eq. 19, with the shell thickness h as in HOOD)

    with the rest area A_f, Lame parameters mu, lambda (Pa) and thickness h (m) of ``rest.material``.

    Args:
        x: (V, 3) positions, meters (typically x_{t+1}); leading batch dims are allowed.
        rest: precomputed rest state.

    Returns:
        scalar energy, J (0 at rest, invariant to rigid motion).
    """
    x0, x1, x2 = gather_corners_cm(coordinate_major(x), rest.faces)  # (3, ..., F) each
    e1, e2 = x1 - x0, x2 - x0  # the columns of D_s
    a = rest.dm_inv  # (F, 2, 2)
    f0 = e1 * a[:, 0, 0] + e2 * a[:, 1, 0]  # columns of F = D_s D_m^-1, coordinate-major
    f1 = e1 * a[:, 0, 1] + e2 * a[:, 1, 1]
    g00 = 0.5 * (dot_cm(f0, f0) - 1.0)  # Green strain from the right Cauchy-Green C = F^T F
    g11 = 0.5 * (dot_cm(f1, f1) - 1.0)
    g01 = 0.5 * dot_cm(f0, f1)
    tr = g00 + g11
    tr_gg = g00 * g00 + g11 * g11 + 2.0 * g01 * g01
    m = rest.material
    density = m.lame_mu * tr_gg + 0.5 * m.lame_lambda * tr * tr  # = tr(S^T G)
    return (rest.rest_area * m.thickness * density).sum()
