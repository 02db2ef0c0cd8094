"""Hierarchical message-passing processor (paper §3.2): residual blocks over named edge sets, visited on a
fine -> coarse -> fine schedule over the anchor levels.

Edge update (first layer split for speed, DESIGN.md "Speed facts"):
``W·[h_s, h_r, e] = (W_s h)[s] + (W_r h)[r] + W_e e``, so the node-sized products are computed once per node
and gathered onto the edges instead of concatenating per edge. Edges without a latent sender (body world
edges: body vertices are not graph nodes) drop the sender term. Updates are residual, messages are summed
onto receivers, the node MLP sees ``[h, Σ messages of each edge set]``.

Level changes: going down pools the nodes by the mean over each anchor's cluster; going up adds the change
the coarse level made to every fine node of the cluster (``h_f += (h_c_out - h_c_in)[parent]``).
"""

from __future__ import annotations

import torch
from torch import nn

from smln.model.mlp import MLP, mlp_tail


class EdgeModel(nn.Module):
    """Residual edge update with the first layer split into node-sized products.

    Args:
        latent: latent size of nodes and edges.
        num_hidden_layers: hidden layers of the edge MLP (width = latent).
        has_sender: False for edge sets whose senders are not graph nodes (body edges).
    """

    def __init__(self, latent: int, num_hidden_layers: int, has_sender: bool = True) -> None:
        super().__init__()
        self.has_sender = has_sender
        self.node_proj = nn.Linear(latent, latent * (2 if has_sender else 1), bias=False)
        self.edge_proj = nn.Linear(latent, latent)
        self.tail = nn.Sequential(*mlp_tail(latent, latent, num_hidden_layers, layer_norm=True))

    def forward(
        self, h: torch.Tensor, e: torch.Tensor, senders: torch.Tensor | None, receivers: torch.Tensor
    ) -> torch.Tensor:
        """New edge latents (E, L) from node latents h (N, L), edge latents e (E, L), indices (E,).

        Written to touch the (E, L) tensors as few times as possible (they dominate the step on CPU): the
        edge bias is added to the node-sized sender (or receiver) product before the gather, the edge product
        is accumulated in place with ``addmm_`` and the first ReLU runs in place.
        """
        lat = e.shape[-1]
        proj = self.node_proj(h)
        if self.has_sender:
            z = (proj[:, :lat] + self.edge_proj.bias).index_select(0, senders)
            z += proj[:, lat:].index_select(0, receivers)
        else:
            z = (proj + self.edge_proj.bias).index_select(0, receivers)
        z.addmm_(e, self.edge_proj.weight.t())
        z = torch.relu_(z)
        return e + self.tail[1:](z)


class MessagePassingBlock(nn.Module):
    """One residual message-passing step over a fixed list of edge sets.

    Args:
        latent: latent size.
        edge_sets: names of the edge sets, in the order the node MLP concatenates their sums.
        senderless: names of the edge sets without latent senders.
        num_hidden_layers: hidden layers of every MLP.
    """

    def __init__(
        self, latent: int, edge_sets: tuple[str, ...], senderless: tuple[str, ...], num_hidden_layers: int
    ) -> None:
        super().__init__()
        self.edge_sets = edge_sets
        self.edge_models = nn.ModuleDict(
            {name: EdgeModel(latent, num_hidden_layers, has_sender=name not in senderless) for name in edge_sets}
        )
        self.node_model = MLP(latent * (1 + len(edge_sets)), latent, latent, num_hidden_layers)

    def forward(
        self,
        h: torch.Tensor,
        edges: dict[str, tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]],
    ) -> tuple[torch.Tensor, dict[str, tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]]]:
        """Args: h (N, L); edges: name -> (senders (E,) or None, receivers (E,), latents (E, L)).

        Returns: the new h and the edge dict with updated latents.
        """
        lat = h.shape[1]
        parts = [h]
        new_edges = {}
        for name in self.edge_sets:
            s, r, e = edges[name]
            e = self.edge_models[name](h, e, s, r)
            new_edges[name] = (s, r, e)
            parts.append(h.new_zeros(h.shape[0], lat).index_add_(0, r, e))
        return h + self.node_model(torch.cat(parts, dim=-1)), new_edges


FINE_EDGE_SETS = ("mesh", "virtual", "body")


class Processor(nn.Module):
    """Blocks visited along ``schedule`` = ((level, steps), ...), starting and ending at level 0.

    Level 0 uses the fine edge sets (mesh, virtual, body); level k >= 1 uses the anchor edges of level k.
    Consecutive schedule entries must differ by exactly one level.
    """

    def __init__(self, latent: int, schedule: tuple[tuple[int, int], ...], num_hidden_layers: int) -> None:
        super().__init__()
        self.schedule = tuple((int(lv), int(n)) for lv, n in schedule)
        blocks = []
        for lv, n in self.schedule:
            for _ in range(n):
                if lv == 0:
                    blocks.append(MessagePassingBlock(latent, FINE_EDGE_SETS, ("body",), num_hidden_layers))
                else:
                    blocks.append(MessagePassingBlock(latent, ("coarse",), (), num_hidden_layers))
        self.blocks = nn.ModuleList(blocks)

    def forward(
        self,
        h: torch.Tensor,
        fine_edges: dict[str, tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]],
        coarse_edges: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
        parents: list[torch.Tensor],
        sizes: list[int] | None = None,
        inv_counts: list[torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Run the schedule.

        Args:
            h: (V, L) fine node latents.
            fine_edges: name -> (senders, receivers, latents) for the fine edge sets.
            coarse_edges: per anchor level k (index k-1): (senders, receivers, latents), local indices.
            parents: per anchor level k (index k-1): (N_{k-1},) index of each previous-level node's anchor.
            sizes: per anchor level, N_k (``GraphTopology.level_sizes``); None = derived from ``parents``
                (a host sync per pooling).
            inv_counts: per anchor level, (N_k, 1) 1 / cluster size (``GraphTopology.level_inv_count``);
                None = counted per call.

        Returns:
            (V, L) fine node latents after the schedule.
        """
        stack: list[torch.Tensor] = [h]  # latents per visited level; stack[k] = level k
        entry: list[torch.Tensor] = [h]  # latents of each level when it was entered from above
        coarse = [e for e in coarse_edges]
        level = 0
        bi = 0
        for lv, n in self.schedule:
            while level < lv:  # pool down
                par = parents[level]
                if sizes is not None:
                    n_c = sizes[level]
                else:
                    n_c = int(par.max().item()) + 1 if par.numel() else 0
                src = stack[level]
                summed = src.new_zeros(n_c, src.shape[1]).index_add_(0, par, src)
                if inv_counts is not None:
                    pooled = summed * inv_counts[level].to(src.dtype)
                else:
                    cnt = src.new_zeros(n_c).index_add_(0, par, torch.ones_like(par, dtype=src.dtype))
                    pooled = summed / cnt.clamp_min(1.0).unsqueeze(-1)
                level += 1
                stack = stack[:level] + [pooled]
                entry = entry[:level] + [pooled]
            while level > lv:  # unpool up
                delta = stack[level] - entry[level]
                par = parents[level - 1]
                stack[level - 1] = stack[level - 1] + delta[par]
                level -= 1
                stack = stack[: level + 1]
                entry = entry[: level + 1]
            for _ in range(n):
                blk = self.blocks[bi]
                bi += 1
                if lv == 0:
                    stack[0], fine_edges = blk(stack[0], fine_edges)
                else:
                    s, r, e = coarse[lv - 1]
                    stack[lv], upd = blk(stack[lv], {"coarse": (s, r, e)})
                    coarse[lv - 1] = upd["coarse"]
        while level > 0:
            delta = stack[level] - entry[level]
            stack[level - 1] = stack[level - 1] + delta[parents[level - 1]]
            level -= 1
        return stack[0]
