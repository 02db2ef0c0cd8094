"""Carry a trained model's weights over to a wider input layout, so fine-tuning starts from the same function.

Session 5 added the body normal and the signed distance to the body world edge features (9 -> 13 columns,
:mod:`smln.graph.multilayer`). :func:`widen_body_edges` copies every weight of a 9-column model into a
13-column one, with zero weights on the new input columns of the body encoder, so the widened model predicts
exactly what the old one did until training gives those columns weight. The body edge normaliser keeps its
statistics for the old columns and takes those of the new ones from samples of real features.
"""

from __future__ import annotations

import re

import torch
from torch import nn

from smln.graph import LEGACY_BODY_EDGE_DIM
from smln.model.smln import SMLN, SMLNConfig


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


def add_body_repulsion(old: SMLN, new: SMLN, push_fraction: float = 1.0) -> None:
    """Load ``old`` (no body stage) into ``new`` (the same config plus ``body_repulsion=True``) in place.

    Every weight is copied; the new body stage starts as :meth:`RepulsionLayer.init_as_projection` with
    ``push_fraction``: at the start of fine-tuning it pushes every garment vertex closer to the body than its
    threshold (not deeper than 2 cm) that fraction of the way onto the threshold (1: like the collision
    projection), and training shapes it.

    Raises:
        ValueError: if the configs differ in anything else.
    """
    oc, nc = old.config.to_dict(), new.config.to_dict()
    if oc.pop("body_repulsion") or not nc.pop("body_repulsion"):
        raise ValueError("add_body_repulsion needs a model without the body stage and one with it")
    oc.pop("body_repulsion_threshold")
    nc.pop("body_repulsion_threshold")
    if oc != nc:
        raise ValueError(f"configs differ in more than the body stage: {sorted(k for k in oc if oc[k] != nc[k])}")
    new.body_repulsion.init_as_projection(push_fraction)
    state = new.state_dict()
    state.update(old.state_dict())
    new.load_state_dict(state, strict=True)


GROWABLE_FIELDS = ("mlp_hidden_layers", "schedule")
_BLOCK_KEY = re.compile(r"^processor\.blocks\.(\d+)\.")
# a Linear/LayerNorm of an SMLN MLP (encoders, decoder, processor node MLPs) or of an edge model's tail
_LAYER_KEY = re.compile(r"^(.*(?:encoder|encoders\.\d+|decoder|node_model|(?P<tail>tail)))\.(\d+)\.(weight|bias)$")


def growth_error(old: SMLNConfig, new: SMLNConfig) -> str | None:
    """Why ``new`` is not a growth of ``old`` (None if it is).

    A growth keeps every field except :data:`GROWABLE_FIELDS`; ``new.mlp_hidden_layers >= old``'s, and
    ``new.schedule`` visits the same levels in the same order with at least as many steps at each visit.
    """
    oc, nc = old.to_dict(), new.to_dict()
    for name in GROWABLE_FIELDS:
        oc.pop(name)
        nc.pop(name)
    if oc != nc:
        differ = sorted(k for k in oc if oc[k] != nc.get(k))
        return f"configs differ in more than {GROWABLE_FIELDS}: {differ}"
    if new.mlp_hidden_layers < old.mlp_hidden_layers:
        return f"mlp_hidden_layers cannot shrink ({old.mlp_hidden_layers} -> {new.mlp_hidden_layers})"
    if [lv for lv, _ in new.schedule] != [lv for lv, _ in old.schedule]:
        return "the schedule must visit the same levels in the same order"
    if any(n_new < n_old for (_, n_old), (_, n_new) in zip(old.schedule, new.schedule, strict=True)):
        return "the schedule cannot lose steps"
    return None


def _block_index_map(old: SMLNConfig, new: SMLNConfig) -> tuple[dict[int, int], list[int]]:
    """Old processor block index -> new index (old blocks first at each schedule visit), and the added blocks."""
    mapping: dict[int, int] = {}
    added: list[int] = []
    bo = bn = 0
    for (_, n_old), (_, n_new) in zip(old.schedule, new.schedule, strict=True):
        for i in range(n_new):
            if i < n_old:
                mapping[bo + i] = bn + i
            else:
                added.append(bn + i)
        bo += n_old
        bn += n_new
    return mapping, added


def grow(old: SMLN, new: SMLN) -> None:
    """Load ``old`` into the deeper ``new`` in place so that ``new`` computes the same function (net2deeper).

    Two kinds of growth (:func:`growth_error` says which configs qualify):

    - more hidden layers per MLP (``mlp_hidden_layers`` n -> m): every encoder, processor and decoder MLP gets
      m - n extra ``Linear(L, L)`` layers right before its output layer, set to the identity with zero bias. Each
      follows a ReLU, so ``ReLU(I·relu(z)) = relu(z)``: the output is unchanged and training can move them.
      The repulsion layer's MLP is not an SMLN MLP (fixed width and depth, paper §3.3) and is copied as is.
    - more message-passing steps at a schedule visit: the old blocks run first, the added ones after them. An
      added block's edge and node MLPs end in a LayerNorm whose scale and shift start at zero, so its residual
      updates are zero (the block is the identity) while the scale still receives gradient.

    Normaliser statistics, the repulsion layer and every other weight are copied.

    Raises:
        ValueError: if ``new``'s config is not a growth of ``old``'s.
    """
    oc, nc = old.config, new.config
    why = growth_error(oc, nc)
    if why is not None:
        raise ValueError(f"cannot grow the model: {why}")
    shift = 2 * (nc.mlp_hidden_layers - oc.mlp_hidden_layers)
    n_old = oc.mlp_hidden_layers
    blocks, added = _block_index_map(oc, nc)
    with torch.no_grad():
        for module in new.modules():  # the inserted hidden layers: identity
            seq, first = _insertion_point(module, n_old)
            if seq is None:
                continue
            for k in range(first, first + shift, 2):
                seq[k].weight.copy_(torch.eye(seq[k].weight.shape[0]))
                seq[k].bias.zero_()
        for b in added:  # the added blocks: residual updates start at zero
            blk = new.processor.blocks[b]
            for norm in [blk.node_model[-1], *(em.tail[-1] for em in blk.edge_models.values())]:
                norm.weight.zero_()
                norm.bias.zero_()
    state = new.state_dict()
    for key, value in old.state_dict().items():
        state[_grown_key(key, blocks, shift, n_old)] = value
    new.load_state_dict(state, strict=True)


def _insertion_point(module: nn.Module, n_old: int) -> tuple[nn.Sequential | None, int]:
    """(sequential, index of its first inserted layer) for an SMLN MLP or an edge model's tail, else (None, 0).

    With ``n_old`` hidden layers an MLP's output Linear sits at index 2·n_old (Linear, ReLU, ..., Linear) and a
    tail's at 2·n_old - 1 (the tail starts with the ReLU after the split first layer); the inserted layers go there.
    """
    from smln.model.mlp import MLP
    from smln.model.processor import EdgeModel

    if isinstance(module, MLP):
        return module, 2 * n_old
    if isinstance(module, EdgeModel):
        return module.tail, 2 * n_old - 1
    return None, 0


def _grown_key(key: str, blocks: dict[int, int], shift: int, n_old: int) -> str:
    """The state-dict key of ``key`` (an old model's) in the grown model: processor blocks renumbered, layers at or
    after the insertion point of their MLP (:func:`_insertion_point`) moved ``shift`` places on."""
    key = _BLOCK_KEY.sub(lambda m: f"processor.blocks.{blocks[int(m.group(1))]}.", key)
    if m := _LAYER_KEY.match(key):
        k = int(m.group(3))
        first = 2 * n_old - 1 if m.group("tail") else 2 * n_old
        return f"{m.group(1)}.{k + shift if k >= first else k}.{m.group(4)}"
    return key
