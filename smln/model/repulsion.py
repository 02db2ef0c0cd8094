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

import math

import torch
from torch import nn
from torch.nn import functional as F


class RepulsionLayer(nn.Module):
    """Eq. 14-16. 3-layer ReLU MLP 4 -> hidden -> hidden -> 1.

    Args:
        threshold: activation distance along the inner normal, m (default 5 mm).
        hidden: MLP width (paper: 32).
        max_depth: pairs whose outer vertex is deeper than this behind the inner vertex's normal plane are left
            alone, m (default: none). The body stage (:class:`smln.model.smln.SMLN`) uses 2 cm: deeper than that
            the nearest-vertex test is mostly wrong (a skirt between the legs), as for
            :data:`smln.projection.BODY_MAX_DEPTH`.
    """

    def __init__(self, threshold: float = 0.005, hidden: int = 32, max_depth: float = float("inf")) -> None:
        super().__init__()
        self.threshold = float(threshold)
        self.max_depth = float(max_depth)
        self.mlp = nn.Sequential(
            nn.Linear(4, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1)
        )

    def init_as_projection(self, fraction: float = 1.0) -> None:
        """Weights for which every active pair is pushed ``fraction`` of the way to the threshold:
        ``softplus(MLP) = fraction`` for all inputs (last layer zero, bias ln(e^fraction - 1)), so
        ``a = fraction (threshold - E_r) n_j``; 1 = the collision projection of :mod:`smln.projection` in one pass.
        A start for training a new stage (the body stage of a fine-tune).

        Raises:
            ValueError: unless 0 < fraction <= 2.
        """
        if not 0.0 < fraction <= 2.0:
            raise ValueError(f"fraction must be in (0, 2], got {fraction!r}")
        with torch.no_grad():
            last = self.mlp[-1]
            last.weight.zero_()
            last.bias.fill_(math.log(math.expm1(fraction)))

    def forward(
        self,
        x_cur: torch.Tensor,
        x_hat: torch.Tensor,
        normals_hat: torch.Tensor,
        pairs: torch.Tensor,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Repulsion acceleration between garment layers.

        Args:
            x_cur: (V, 3) positions at t, m.
            x_hat: (V, 3) predicted positions x_t + v_t + p, m.
            normals_hat: (V, 3) unit vertex normals at ``x_hat`` (only inner-layer rows are read).
            pairs: (2, P) int64 (outer i, inner j).

        Returns:
            a (V, 3) m/frame^2 and extras ``{"active_pairs": (2, P_a), "magnitude": (P_a,),
            "signed_distance": (P,)}``.
        """
        i, j = pairs[0], pairs[1]
        a, ex = self.push(i, x_cur[i], x_hat[i], x_cur[j], x_hat[j], normals_hat[j], x_hat.shape[0])
        ex["active_pairs"] = torch.stack([i[ex["active"]], j[ex["active"]]])
        del ex["active"]
        return a, ex

    def push(
        self,
        outer: torch.Tensor,
        outer_cur: torch.Tensor,
        outer_hat: torch.Tensor,
        inner_cur: torch.Tensor,
        inner_next: torch.Tensor,
        inner_normal: torch.Tensor,
        num_vertices: int,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The push of P pairs given per pair (the body stage's inner side is the body, not a garment row).

        Args:
            outer: (P,) int64 garment vertex of each pair (the one pushed).
            outer_cur, outer_hat: (P, 3) its position at t and predicted at t+1, m.
            inner_cur, inner_next: (P, 3) the inner partner at t and at t+1 (predicted, or the body's), m.
            inner_normal: (P, 3) the partner's unit normal at t+1.
            num_vertices: V, rows of the returned acceleration.

        Returns:
            a (V, 3) m/frame^2 (summed over pairs) and extras ``{"active": (P_a,) int64 pair rows processed,
            "magnitude": (P_a,), "signed_distance": (P,)}``.
        """
        e_r = ((outer_hat - inner_next) * inner_normal).sum(-1)
        thr = self.threshold
        active = e_r < thr
        if math.isfinite(self.max_depth):
            active = active & (e_r > -self.max_depth)
        idx = torch.nonzero(active, as_tuple=True)[0]
        na, ea = inner_normal[idx], e_r[idx]
        la = outer_hat[idx] - inner_next[idx]
        rel_v = (outer_hat[idx] - outer_cur[idx]) - (inner_next[idx] - inner_cur[idx])
        feats = torch.stack([la.norm(dim=-1), ea, thr - ea, (rel_v * na).sum(-1)], dim=-1) / thr
        mag = F.softplus(self.mlp(feats).squeeze(-1)) * (thr - ea)
        a = outer_hat.new_zeros((num_vertices, 3)).index_add(0, outer[idx], mag.unsqueeze(-1) * na)
        return a, {"active": idx, "magnitude": mag, "signed_distance": e_r}
