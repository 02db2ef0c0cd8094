"""The training objective of one step (paper Eq. 17 plus inertia and body collision)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from smln.cloth import DT
from smln.geometry import PointTree, build_tree, coordinate_major, nearest_vertices, vertex_normals, vertex_normals_cm
from smln.losses.bending import bending_energy
from smln.losses.collision import COLLISION_EPS, collision_energy
from smln.losses.friction import friction_energy, layer_friction_energy
from smln.losses.gravity import gravity_energy
from smln.losses.inertia import inertia_energy
from smln.losses.repulsion import REPULSION_EPS, layer_pairs, repulsion_energy_cm
from smln.losses.rest import ClothRest
from smln.losses.stretch import stretch_energy

TRAINING_REPULSION = 1e4
"""λr used for training and the reference solver (the paper's 1e3 is too soft here; see LossWeights.training)."""


@dataclass
class LossWeights:
    """Weights lambda of Eq. 17 (paper: stretch = bend = gravity = 1, friction = 1.5, repulsion = 1e3).

    Added terms: ``inertia`` = 1 (the implicit-Euler kinetic term; with it the energies are one consistent
    incremental potential in J) and ``collision`` = 1e4 J/m^3 on the cubic body penalty (m^3): at 1 mm inside
    the 3 mm clearance it pushes back with 3e4 * (1e-3)^2 = 0.03 N, ~150x the weight of a 1 cm^2 cloth
    vertex (2e-4 N), and a 3 mm penetration costs 1e4 * (6e-3)^3 = 2e-3 J, far more than any gravity or
    inertia gain of that vertex; 1e4-1e5 behaved alike in our probe (HOOD ramps 5e3 -> 5e5).
    """

    stretch: float = 1.0
    bending: float = 1.0
    gravity: float = 1.0
    friction: float = 1.5
    repulsion: float = 1e3
    inertia: float = 1.0
    collision: float = 1e4
    collision_eps: float = COLLISION_EPS
    """Clearance of the body penalty, meters (:data:`smln.losses.collision.COLLISION_EPS`, 3 mm); also the body
    friction's contact distance, since resting cloth sits about there (equal to ``FRICTION_RADIUS`` by default)."""
    repulsion_eps: float = REPULSION_EPS
    """Clearance between adjacent layers of the repulsion loss (Eq. 25), meters
    (:data:`smln.losses.repulsion.REPULSION_EPS`, 3 mm); also the clearance of the layer friction's contact push."""
    layer_friction: float = 0.0
    """Weight of the friction between adjacent layers (:func:`~smln.losses.friction.layer_friction_energy`);
    0 = off (the paper's Eq. 22 and every run before session 11 hold the cloth against the body only)."""
    layer_friction_radius: float | None = None
    """Contact distance of the layer friction, meters; None = ``repulsion_eps`` + 2 mm
    (:func:`~smln.losses.friction.layer_friction_radius`: 5 mm at the default clearance). Sessions 27-29 trained with
    a 4.5 mm clearance and a fixed 5 mm radius: pass 0.005 to repeat them."""
    layer_friction_contact: bool = False
    """Add the repulsion term's contact force (k = ``repulsion``) to the weight as the layer friction's normal force
    (session 12); off = the weight alone (session 11). Nothing changes where ``repulsion`` is 0 (baseline)."""

    @classmethod
    def training(cls) -> LossWeights:
        """The weights SMLN trains with and the reference solver uses: the paper's, but λr = ``TRAINING_REPULSION``.

        With the paper's λr = 1e3 the repulsion is 10x softer than the body penalty and loses against stretch
        in tight places (a pair interpenetrated by 3 mm, 6 mm short of the clearance, is pushed apart with
        3 * 1e3 * (6e-3)^2 = 0.1 N, the order of the stretch force of one strained 3.5 cm edge); minimising
        the loss itself then leaves the layers
        interpenetrating. Measured with the L-BFGS solver (``bench/solver_weights.py``), tshirt_jacket on
        the test clip 05_01_walk, frames 2-24: L-Coll 4.4 % with λr = 1e3 and a 2 cm pair radius, 3.1 % with
        λr = 1e4, 1.6 % with λr = 1e4 and the 4 cm radius of :data:`~smln.losses.repulsion.PAIR_RADIUS`
        (H-Coll 2.7 → 2.1 %, mean strain 5.3 → 4.7 %); λr = 3e4 raised H-Coll (3.3 %) and strain (5.6 %), a 3e4
        body weight raised strain (6.5 %). Fine-tuning with it took the 120-frame validation L-Coll of the full
        model from 6.4 % to about 1.5 % within 4k steps (docs/RESULTS.md).
        """
        return cls(repulsion=TRAINING_REPULSION)


@dataclass
class BodyStep:
    """The body at t and t+1, with what the losses need at t+1 (normals, KD-tree), built once per step.

    Attributes:
        cur: (Vb, 3) body vertices at t, meters; next: (Vb, 3) at t+1.
        normals_next: (Vb, 3) unit outward vertex normals at t+1.
        tree_next: KD-tree over ``next`` (CPU).
    """

    cur: torch.Tensor
    next: torch.Tensor
    normals_next: torch.Tensor
    tree_next: PointTree

    @classmethod
    def from_vertices(
        cls, body_cur: torch.Tensor, body_next: torch.Tensor, body_faces: torch.Tensor
    ) -> BodyStep:
        """Compute the normals and the tree at t+1 (body_faces: (Fb, 3) int64)."""
        body_cur, body_next = body_cur.detach(), body_next.detach()
        return cls(
            cur=body_cur,
            next=body_next,
            normals_next=vertex_normals(body_next, body_faces.to(body_next.device)),
            tree_next=build_tree(body_next),
        )


def total_loss(
    x_prev: torch.Tensor,
    x_cur: torch.Tensor,
    x_next: torch.Tensor,
    body: BodyStep,
    rest: ClothRest,
    weights: LossWeights | None = None,
    dt: float = DT,
    pairs: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """L = sum_k w_k E_k over stretch, bending, gravity, friction, repulsion, inertia, collision (and, when its
    weight is set, the friction between layers).

    Only ``x_next`` is expected to carry gradient (x_prev, x_cur are history). Pinned vertices of ``x_next``
    should already hold their skinned positions; gravity, inertia, friction and collision skip them, stretch
    and bending include them (their triangles pull on the free neighbours). Terms with weight 0 are skipped.

    Args:
        x_prev, x_cur, x_next: (V, 3) cloth positions at t-1, t, t+1, meters, float32.
        body: :class:`BodyStep` for this step.
        rest: :class:`~smln.losses.rest.ClothRest` of the cloth.
        weights: :class:`LossWeights` (defaults if None).
        dt: time step, seconds.
        pairs: (P, 2) cross-layer pairs from :func:`~smln.losses.repulsion.layer_pairs` at step t; computed
            from ``x_cur`` if None (pass them in when calling repeatedly for the same step, e.g. L-BFGS).

    Returns:
        loss: scalar tensor (weighted sum, J); terms: unweighted value of each term plus "total" (floats).
    """
    w = weights or LossWeights()
    terms: dict[str, torch.Tensor] = {}
    if w.stretch:
        terms["stretch"] = stretch_energy(x_next, rest)
    if w.bending:
        terms["bending"] = bending_energy(x_next, rest)
    if w.gravity:
        terms["gravity"] = gravity_energy(x_next, rest)
    if w.inertia:
        terms["inertia"] = inertia_energy(x_prev, x_cur, x_next, rest, dt)
    if w.collision or w.friction:
        idx, _ = nearest_vertices(x_next, tree=body.tree_next)
        if w.collision:
            terms["collision"] = collision_energy(x_next, body.next, body.normals_next, rest, idx=idx,
                                                   eps=w.collision_eps)
        if w.friction:
            # contact = within the body penalty's clearance, where resting cloth sits (3 mm by default)
            terms["friction"] = friction_energy(
                x_cur, x_next, body.cur, body.next, body.normals_next, rest, idx=idx, radius=w.collision_eps
            )
    if (w.repulsion or w.layer_friction) and rest.num_layers > 1:
        if pairs is None:
            pairs = layer_pairs(x_cur.detach(), rest)
        xt = coordinate_major(x_next)
        nt = vertex_normals_cm(xt, rest.faces)
        if w.repulsion:
            terms["repulsion"] = repulsion_energy_cm(xt, nt, pairs, rest, eps=w.repulsion_eps)
        if w.layer_friction:
            terms["layer_friction"] = layer_friction_energy(
                x_cur, x_next, nt.t(), pairs, rest,
                radius=w.layer_friction_radius, contact_stiffness=w.repulsion if w.layer_friction_contact else 0.0,
                eps=w.repulsion_eps)
    wd = asdict(w)
    loss = sum(wd[k] * v for k, v in terms.items())
    values = {k: float(v.detach()) for k, v in terms.items()}
    values["total"] = float(loss.detach())
    return loss, values


def pre_layer_contact_loss(
    x_hat: torch.Tensor,
    body: BodyStep,
    rest: ClothRest,
    weights: LossWeights,
    repulsion_factor: float = 0.0,
    collision_factor: float = 0.0,
    pairs: torch.Tensor | None = None,
    x_cur: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The contact terms of :func:`total_loss` read on the network's own prediction x̂, before the repulsion layer.

    Our extension of the paper's objective (session 40): Eq. 17 scores only x_{t+1} = x̂ + a, so with the repulsion
    layer on, the network is never asked to keep the layers (or the body) apart itself: the layer does it. These
    terms ask it to, the layer staying a safety net: ``repulsion_factor * weights.repulsion *`` the repulsion energy
    (Eq. 23-25, same clearance and pairs as the main term) and ``collision_factor * weights.collision *`` the body
    penalty, both at x̂. A factor of 0 skips its term.

    Args:
        x_hat: (V, 3) meters, x_t + v_t + p (pinned vertices should already hold their targets).
        body: :class:`BodyStep` of this step.
        rest: :class:`~smln.losses.rest.ClothRest` of the cloth.
        weights: the run's :class:`LossWeights` (``repulsion``, ``collision`` and their clearances).
        repulsion_factor, collision_factor: multipliers of those weights, >= 0.
        pairs: (P, 2) cross-layer pairs at step t (:func:`~smln.losses.repulsion.layer_pairs`); computed from
            ``x_cur`` if None.
        x_cur: (V, 3) positions at t, meters; needed only when ``pairs`` is None.

    Returns:
        loss: scalar tensor (J); terms: unweighted ``pre_repulsion`` / ``pre_collision`` (m^3) of the terms computed.
    """
    if repulsion_factor < 0 or collision_factor < 0:
        raise ValueError(f"pre-layer factors must be >= 0, got {repulsion_factor!r}, {collision_factor!r}")
    terms: dict[str, torch.Tensor] = {}
    loss = x_hat.new_zeros(())
    if collision_factor and weights.collision:
        idx, _ = nearest_vertices(x_hat, tree=body.tree_next)
        terms["pre_collision"] = collision_energy(x_hat, body.next, body.normals_next, rest, idx=idx,
                                                  eps=weights.collision_eps)
        loss = loss + collision_factor * weights.collision * terms["pre_collision"]
    if repulsion_factor and weights.repulsion and rest.num_layers > 1:
        if pairs is None:
            if x_cur is None:
                raise ValueError("pre_layer_contact_loss needs pairs or x_cur")
            pairs = layer_pairs(x_cur.detach(), rest)
        xt = coordinate_major(x_hat)
        terms["pre_repulsion"] = repulsion_energy_cm(xt, vertex_normals_cm(xt, rest.faces), pairs, rest,
                                                     eps=weights.repulsion_eps)
        loss = loss + repulsion_factor * weights.repulsion * terms["pre_repulsion"]
    return loss, {k: float(v.detach()) for k, v in terms.items()}
