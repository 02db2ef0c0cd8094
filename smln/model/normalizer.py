"""Running per-feature mean/std normalisation (MeshGraphNets), frozen after a number of accumulations."""

from __future__ import annotations

import torch
from torch import nn


class Normalizer(nn.Module):
    """Normalises features with statistics accumulated during the first ``max_accumulations`` training calls.

    The statistics live in buffers (``count``, ``total``, ``total_sq``, float64) so they travel with the
    weights in a checkpoint. Before any accumulation the normaliser is the identity. The standard deviation
    is floored at ``std_floor`` so features that are constant during training (Δt, material) do not explode
    when they later change.

    Args:
        size: number of features D.
        max_accumulations: number of training forward calls that update the statistics.
        std_floor: lower bound of the standard deviation, in feature units.
    """

    def __init__(self, size: int, max_accumulations: int = 200, std_floor: float = 1e-4) -> None:
        super().__init__()
        self.max_accumulations = int(max_accumulations)
        self.std_floor = float(std_floor)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("calls", torch.zeros((), dtype=torch.float64))
        self.register_buffer("total", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("total_sq", torch.zeros(size, dtype=torch.float64))
        self._cache: tuple[tuple, torch.Tensor, torch.Tensor] | None = None

    @property
    def frozen(self) -> bool:
        return bool(self.calls.item() >= self.max_accumulations)

    def _stats_key(self) -> tuple:
        """Changes whenever a statistics buffer is replaced or modified in place (accumulation, loading)."""
        bufs = (self.count, self.total, self.total_sq)
        return tuple((id(b), b._version, b.device) for b in bufs)

    def mean_std(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Current (D,) float32 mean and std (0 and 1 before any data), cached until the statistics change
        (no float64 math or host sync per step once frozen)."""
        key = self._stats_key()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        n = self.count.clamp_min(1.0)
        mean = self.total / n
        var = (self.total_sq / n - mean * mean).clamp_min(0.0)
        std = var.sqrt().clamp_min(self.std_floor)
        if self.count.item() == 0:
            mean, std = torch.zeros_like(mean), torch.ones_like(std)
        mean, std = mean.float(), std.float()
        self._cache = (key, mean, std)
        return mean, std

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, D) -> (N, D) normalised; accumulates statistics while training and not yet frozen."""
        if self.training and not self.frozen and x.shape[0] > 0:
            with torch.no_grad():
                xd = x.detach().double()
                self.count += xd.shape[0]
                self.total += xd.sum(0)
                self.total_sq += (xd * xd).sum(0)
                self.calls += 1
        mean, std = self.mean_std()
        return (x - mean) / std
