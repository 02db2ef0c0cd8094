"""Collision projection: an optional post-step that moves penetrating cloth vertices back out (rollout option).

SMLN itself (paper §3) resolves collisions only through what the network learned: the body-collision and
repulsion losses during training and the repulsion layer at inference. Physics simulators and production
cloth pipelines add a geometric collision response after each step; this module is that response, off by
default and reported separately in the evaluation, so that the learned model is always measured on its own.

Body projection: every free cloth vertex i with nearest body vertex h (Euclidean, the same test as the H-Coll
metric) and signed distance d_i = (x_i - b_h) . n_h below ``clearance`` (but not deeper than
:data:`BODY_MAX_DEPTH`) moves along n_h to d_i = clearance.
Repeated ``iterations`` times because the nearest body vertex may change after the move (concave regions).

Layer projection: layers from the second-innermost outward, each free vertex of layer k whose nearest vertex
j of layer k-1 (already projected, with its vertex normal n_j at the projected positions) lies within
``LAYER_RADIUS`` and whose signed distance (x_i - x_j) . n_j is below ``layer_clearance`` moves along n_j to
that clearance. Pairs farther apart are left alone: beyond an inner layer's hem the nearest inner vertex says
nothing about penetration (the same reason as :data:`smln.losses.repulsion.PAIR_RADIUS`).

The moved positions become the new state, so the next step's velocity carries the push (an inelastic
collision response, as in position-based dynamics).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smln.geometry import PointTree, build_tree, coordinate_major, dot_cm, vertex_normals_cm
from smln.geometry.mesh_np import vertex_normals_at
from smln.losses.rest import ClothRest

BODY_CLEARANCE = 1e-3
"""Distance the body projection leaves between a moved vertex and the body's vertex-normal plane, meters."""

BODY_MAX_DEPTH = 2e-2
"""Vertices deeper than this behind their nearest body vertex's normal plane are left alone, meters: at such depths
the nearest-vertex test is mostly wrong (a skirt between the legs, a sleeve near the torso) and a push of
several centimetres in one step tears the cloth (tanktop_dress on the test pirouette fell back to skinning in 41 of
141 frames without this bound; with it, in the same 7 frames as without any projection)."""

LAYER_CLEARANCE = 1e-3
"""Distance the layer projection leaves in front of the layer beneath, meters."""

LAYER_RADIUS = 2e-2
"""Only inner vertices closer than this are used by the layer projection, meters."""


@dataclass
class ProjectionResult:
    """Projected positions and what moved.

    Attributes:
        x: (V, 3) float32 projected positions, meters.
        moved: (V,) bool, vertices the projection moved.
        displacement: (V,) float32 length of each vertex's total move, meters.
    """

    x: torch.Tensor
    moved: torch.Tensor
    displacement: torch.Tensor


def _push(x: torch.Tensor, sel: torch.Tensor, ref_at: torch.Tensor, normals_at: torch.Tensor, clearance: float,
          max_depth: float = float("inf")) -> tuple[torch.Tensor, torch.Tensor]:
    """Move the rows ``sel`` of ``x`` along their partners' normals to ``clearance`` if closer.

    Args:
        x: (V, 3) positions (returned moved, a new tensor); sel: (N,) int64 rows of x; ref_at, normals_at: (N, 3)
        each selected row's partner vertex and its unit normal; max_depth: rows deeper than this behind the
        partner's plane are not moved, meters.

    Returns:
        the moved positions, and (N,) bool: which selected rows moved.
    """
    d = dot_cm(coordinate_major(x.index_select(0, sel) - ref_at), coordinate_major(normals_at))
    push = torch.where(d > -max_depth, torch.clamp(clearance - d, min=0.0), torch.zeros_like(d))
    return x.index_add(0, sel, push.unsqueeze(1) * normals_at), push > 0


def project_out_of_body(
    x: torch.Tensor,
    body: torch.Tensor,
    body_faces: torch.Tensor,
    free: torch.Tensor,
    tree: PointTree | None = None,
    clearance: float = BODY_CLEARANCE,
    iterations: int = 2,
    max_depth: float = BODY_MAX_DEPTH,
) -> torch.Tensor:
    """Body projection (module docstring).

    Args:
        x: (V, 3) cloth positions, meters.
        body: (Vb, 3) body vertices at the same frame, meters; body_faces: (Fb, 3) int64.
        free: (V,) bool, vertices that may move (not pinned).
        tree: a prebuilt :func:`~smln.geometry.build_tree` over ``body`` (built if None).
        clearance: target signed distance, meters. iterations: passes.
        max_depth: vertices deeper inside than this are left alone, meters (:data:`BODY_MAX_DEPTH`).

    Returns:
        (V, 3) projected positions (a new tensor; ``x`` is not modified).
    """
    tree = tree if tree is not None else build_tree(body)
    body_t = np.ascontiguousarray(body.detach().cpu().numpy().T)  # coordinate-major numpy, for the normals
    faces_t = np.ascontiguousarray(np.asarray(body_faces.cpu() if isinstance(body_faces, torch.Tensor) else body_faces,
                                              dtype=np.int64).T)
    sel = torch.nonzero(free).squeeze(1)
    for _ in range(iterations):  # passes (2), not a loop over vertices; the second one re-tests the moved rows
        if sel.numel() == 0:
            break
        _, idx = tree.query(x.index_select(0, sel).detach().cpu().numpy())
        ok = idx < tree.n  # non-finite rows have no nearest vertex: left alone (the rollout flags them)
        sel, idx = sel[torch.from_numpy(ok).to(x.device)], idx[ok]
        normals = torch.from_numpy(vertex_normals_at(body_t, faces_t, idx).T).to(x.device, x.dtype)
        near = torch.from_numpy(idx).to(x.device)
        x, moved = _push(x, sel, body.index_select(0, near), normals, clearance, max_depth)
        sel = sel[moved]
    return x


def project_out_of_layers(
    x: torch.Tensor, rest: ClothRest, clearance: float = LAYER_CLEARANCE, radius: float = LAYER_RADIUS
) -> torch.Tensor:
    """Layer projection (module docstring): each layer out of the one beneath, inner to outer.

    Args:
        x: (V, 3) cloth positions, meters (Cloth vertex order); rest: the cloth's faces, layers and pinned mask.
        clearance: target signed distance, meters. radius: pair cut-off, meters.

    Returns:
        (V, 3) projected positions (a new tensor).
    """
    free = ~rest.pinned.to(x.device)
    faces = rest.faces.to(x.device)
    slices = rest.layer_slices
    for k in range(1, len(slices)):  # loop over layers (2-3), not vertices
        inner, outer = slices[k - 1], slices[k]
        normals = vertex_normals_cm(coordinate_major(x), faces).t()  # (V, 3), at the current positions
        sel = torch.arange(outer.start, outer.stop, device=x.device)
        sel = sel[free[sel]]
        tree = build_tree(x[inner])
        dist, idx = tree.query(x.index_select(0, sel).detach().cpu().numpy(), distance_upper_bound=radius)
        close = torch.from_numpy(dist < radius).to(x.device)
        if not bool(close.any()):
            continue
        partner = torch.from_numpy(idx).to(x.device)[close] + inner.start
        x, _ = _push(x, sel[close], x.index_select(0, partner), normals.index_select(0, partner), clearance)
    return x


def project(
    x: torch.Tensor,
    rest: ClothRest,
    body: torch.Tensor | None = None,
    body_faces: torch.Tensor | None = None,
    body_tree: PointTree | None = None,
    layers: bool = False,
) -> ProjectionResult:
    """Body projection (if ``body`` is given), then layer projection (if ``layers``), on one frame.

    Args:
        x: (V, 3) cloth positions, meters.
        rest: the cloth's rest state (pinned mask, faces, layers).
        body: (Vb, 3) body vertices, meters, and body_faces (Fb, 3) int64; None skips the body projection.
        body_tree: prebuilt tree over ``body``.
        layers: also project each layer out of the one beneath.

    Returns:
        :class:`ProjectionResult` (``x`` unchanged if it has a non-finite coordinate).
    """
    x0 = x
    if not bool(torch.isfinite(x).all()):  # a diverged step: nothing to project, the rollout flags the frame
        zero = torch.zeros(x.shape[0], dtype=x.dtype, device=x.device)
        return ProjectionResult(x=x, moved=zero > 0, displacement=zero)
    if body is not None:
        if body_faces is None:
            raise ValueError("the body projection needs body_faces")
        x = project_out_of_body(x, body, body_faces, ~rest.pinned.to(x.device), tree=body_tree)
    if layers and rest.num_layers > 1:
        x = project_out_of_layers(x, rest)
    disp = (x - x0).norm(dim=-1)
    return ProjectionResult(x=x, moved=disp > 0, displacement=disp)
