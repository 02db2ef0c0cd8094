"""Multi-layer perceptrons used by the encoders, processor and decoder (MeshGraphNets style)."""

from __future__ import annotations

from torch import nn


def mlp_tail(hidden: int, out_dim: int, num_hidden_layers: int, layer_norm: bool) -> list[nn.Module]:
    """Layers after the first Linear of an MLP: ReLU, (Linear, ReLU) * (n-1), Linear, [LayerNorm]."""
    mods: list[nn.Module] = [nn.ReLU()]
    for _ in range(num_hidden_layers - 1):
        mods += [nn.Linear(hidden, hidden), nn.ReLU()]
    mods.append(nn.Linear(hidden, out_dim))
    if layer_norm:
        mods.append(nn.LayerNorm(out_dim))
    return mods


class MLP(nn.Sequential):
    """``num_hidden_layers`` hidden ReLU layers of width ``hidden`` and an optional output LayerNorm.

    Args:
        in_dim: input features.
        out_dim: output features.
        hidden: hidden width.
        num_hidden_layers: number of hidden layers (>= 1; default 2 as in MeshGraphNets/HOOD).
        layer_norm: LayerNorm on the output (all MLPs except the decoder).

    Shapes: (..., in_dim) -> (..., out_dim).
    """

    def __init__(
        self, in_dim: int, out_dim: int, hidden: int, num_hidden_layers: int = 2, layer_norm: bool = True
    ) -> None:
        if num_hidden_layers < 1:
            raise ValueError("num_hidden_layers must be >= 1")
        super().__init__(nn.Linear(in_dim, hidden), *mlp_tail(hidden, out_dim, num_hidden_layers, layer_norm))
