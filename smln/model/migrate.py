"""Carry a trained model's weights over to a wider input layout, so fine-tuning starts from the same function.

Session 5 added the body normal and the signed distance to the body world edge features (9 -> 13 columns,
:mod:`smln.graph.multilayer`). :func:`widen_body_edges` copies every weight of a 9-column model into a
13-column one, with zero weights on the new input columns of the body encoder, so the widened model predicts
exactly what the old one did until training gives those columns weight. The body edge normaliser keeps its
statistics for the old columns and takes those of the new ones from samples of real features.
"""

from __future__ import annotations

import torch

from smln.graph import LEGACY_BODY_EDGE_DIM
from smln.model.smln import SMLN


def widen_body_edges(old: SMLN, new: SMLN, new_columns: torch.Tensor) -> None:
    """Load ``old`` (9-column body edges) into ``new`` (13 columns) in place.

    Args:
        old: a model with ``body_normal_features=False``.
        new: a model with the same config except ``body_normal_features=True``.
        new_columns: (M, 4) samples of the new feature columns (body normal at t+1, signed distance, m), M >= 2,
            e.g. the body edges of skinned training states; their mean and variance become the normaliser's
            statistics of these columns (weighted as if seen as often as the old columns were).

    Raises:
        ValueError: if the configs differ in anything else, or the samples are unusable.
    """
    oc, nc = old.config.to_dict(), new.config.to_dict()
    if oc.pop("body_normal_features") or not nc.pop("body_normal_features") or oc != nc:
        raise ValueError("widen_body_edges needs a model without body normal features and one with them, "
                         "otherwise the same config")
    extra = new.config.body_edge_dim - LEGACY_BODY_EDGE_DIM
    if new_columns.ndim != 2 or new_columns.shape[1] != extra or new_columns.shape[0] < 2:
        raise ValueError(f"new_columns must be (M >= 2, {extra}), got {tuple(new_columns.shape)}")
    if not torch.isfinite(new_columns).all():
        raise ValueError("new_columns contains NaN or Inf")
    state = old.state_dict()
    target = new.state_dict()
    first = "body_encoder.0.weight"
    w = torch.zeros_like(target[first])
    w[:, :LEGACY_BODY_EDGE_DIM] = state[first]
    state[first] = w
    count = state["body_norm.count"]
    cols = new_columns.detach().to(torch.float64)
    mean, var = cols.mean(0), cols.var(0, unbiased=False)
    state["body_norm.total"] = torch.cat([state["body_norm.total"], count * mean])
    state["body_norm.total_sq"] = torch.cat([state["body_norm.total_sq"], count * (var + mean * mean)])
    new.load_state_dict(state, strict=True)
