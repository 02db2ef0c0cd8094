"""The garment repulsion layer (paper §3.3, Eq. 14-16): an extra acceleration ``a`` for close or penetrating
cross-layer vertex pairs, predicted by a small MLP from the pair geometry at the predicted next positions.

For every pair (outer vertex i of layer k+1, its nearest vertex j of layer k; the pairs are the virtual edges
found at step t) and the predicted positions ``x̂ = x_t + v_t + p``:

- ``L_ij = x̂_i - x̂_j`` (Eq. 14's edge vector), ``n_j`` = unit vertex normal of the inner layer at ``x̂``;
- ``E_r = L_ij · n_j`` (signed distance of i in front of the inner layer along its normal, m; Eq. 14);
- only pairs with ``E_r < threshold`` are processed (the paper's "edge vectors below the threshold");
- MLP input (4, all divided by ``threshold`` to be unit-free): ``|L_ij|``, ``E_r``, ``threshold - E_r`` (the
  missing clearance), and the relative normal velocity ``((x̂_i - x_i) - (x̂_j - x_j)) · n_j`` (how fast the
  pair closes in the predicted step);
- magnitude ``m = softplus(MLP(...)) * (threshold - E_r)`` (m/frame^2, >= 0; the clearance factor makes the
  push vanish continuously at the threshold and scale with the depth);
- ``a_i += m · n_j`` on the OUTER vertex only. The inner vertex is not pushed: it sits between the outer layer
  and the body, and pushing it inward would trade a layer collision for a body collision.

Vertices in no processed pair get exactly zero; so does everything when all pairs are separated by at least
the threshold (Eq. 16: ``x_{t+1} = x_t + v_t + p + a``).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class RepulsionLayer(nn.Module):
    """Eq. 14-16. 3-layer ReLU MLP 4 -> hidden -> hidden -> 1.

    Args:
        threshold: activation distance along the inner normal, m (default 5 mm).
        hidden: MLP width (paper: 32).
    """

    def __init__(self, threshold: float = 0.005, hidden: int = 32) -> None:
        super().__init__()
        self.threshold = float(threshold)
        self.mlp = nn.Sequential(
            nn.Linear(4, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1)
        )

    def forward(
        self,
        x_cur: torch.Tensor,
        x_hat: torch.Tensor,
        normals_hat: torch.Tensor,
        pairs: torch.Tensor,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Repulsion acceleration.

        Args:
            x_cur: (V, 3) positions at t, m.
            x_hat: (V, 3) predicted positions x_t + v_t + p, m.
            normals_hat: (V, 3) unit vertex normals at ``x_hat`` (only inner-layer rows are read).
            pairs: (2, P) int64 (outer i, inner j).

        Returns:
            a (V, 3) m/frame^2 and extras ``{"active_pairs": (2, P_a), "magnitude": (P_a,),
            "signed_distance": (P,)}``.
        """
        a = torch.zeros_like(x_hat)
        i, j = pairs[0], pairs[1]
        n_j = normals_hat[j]
        lij = x_hat[i] - x_hat[j]
        e_r = (lij * n_j).sum(-1)
        thr = self.threshold
        active = e_r < thr
        idx = torch.nonzero(active, as_tuple=True)[0]
        ia, ja, na, la, ea = i[idx], j[idx], n_j[idx], lij[idx], e_r[idx]
        rel_v = ((x_hat[ia] - x_cur[ia]) - (x_hat[ja] - x_cur[ja]))
        feats = torch.stack(
            [la.norm(dim=-1), ea, thr - ea, (rel_v * na).sum(-1)], dim=-1
        ) / thr
        mag = F.softplus(self.mlp(feats).squeeze(-1)) * (thr - ea)
        a = a.index_add(0, ia, mag.unsqueeze(-1) * na)
        return a, {"active_pairs": torch.stack([ia, ja]), "magnitude": mag, "signed_distance": e_r}
