"""Friction against the body (paper Eq. 22, in HOOD's contact-slip form)."""

from __future__ import annotations

import torch

from smln.cloth import GRAVITY
from smln.geometry import PointTree, coordinate_major, dot_cm, signed_distance_along_normals
from smln.losses.repulsion import REPULSION_EPS
from smln.losses.rest import ClothRest

FRICTION_RADIUS = 3e-3
"""Contact distance, meters: cloth vertices closer than this to the body at t+1 (along its normal)."""

SLIP_SMOOTHING = 1e-4
"""Smoothing c, meters: ||s|| becomes sqrt(||s||^2 + c^2) - c (quadratic below ~0.1 mm, finite gradient)."""


def friction_energy(
    x_cur: torch.Tensor,
    x_next: torch.Tensor,
    body_cur: torch.Tensor,
    body_next: torch.Tensor,
    body_normals_next: torch.Tensor,
    rest: ClothRest,
    idx: torch.Tensor | None = None,
    tree: PointTree | None = None,
    radius: float = FRICTION_RADIUS,
    g: float = GRAVITY,
) -> torch.Tensor:
    """Coulomb-like friction work of the cloth sliding over the body during one step.

    For each free cloth vertex i with nearest body vertex j at t+1 (``idx``) and signed distance
    d_i = (x_i^{t+1} - b_j^{t+1}) . n_j < ``radius`` (contact; decided without gradient):

        s_i = (x_i^{t+1} - x_i^t) - (b_j^{t+1} - b_j^t)       slip relative to the body's own motion
        s_i^T = s_i - (s_i . n_j) n_j                          its tangential part
        E = sum_{i in contact} mu m_i g * (sqrt(||s_i^T||^2 + c^2) - c)

    i.e. the work of a friction force of magnitude mu * m_i * g (normal force approximated by the weight, as
    in HOOD) along the slip. This reads the paper's Eq. 22 "mu m g cos(theta) * distance" with the distance
    being the tangential slip and cos(theta) ~ 1. mu = ``rest.material.friction`` (0.5), c = SLIP_SMOOTHING.

    Args:
        x_cur, x_next: (V, 3) cloth positions at t and t+1, meters.
        body_cur, body_next: (Vb, 3) body vertices at t and t+1.
        body_normals_next: (Vb, 3) unit body vertex normals at t+1.
        rest: masses, free mask, material.
        idx: (V,) nearest body vertex of each x_next vertex (found with ``tree``/a new tree if None).
        radius: contact distance, meters; g: m/s^2.

    Returns:
        scalar energy, J.
    """
    with torch.no_grad():  # contact is decided without gradient
        idx, d = signed_distance_along_normals(x_next, body_next, body_normals_next, idx=idx, tree=tree)
        contact = (d < radius).to(x_next.dtype) * rest.free
        n = coordinate_major(body_normals_next.index_select(0, idx))  # (3, V)
        body_move = coordinate_major(body_next.index_select(0, idx) - body_cur.index_select(0, idx))
    s = coordinate_major(x_next - x_cur) - body_move  # relative slip of the step, (3, V)
    st = s - dot_cm(s, n) * n
    c = SLIP_SMOOTHING
    slip = torch.sqrt(dot_cm(st, st) + c * c) - c
    return (rest.material.friction * g * rest.mass * contact * slip).sum()


LAYER_FRICTION_MARGIN = 2e-3
"""How far beyond the repulsion clearance an outer vertex still counts as touching the layer beneath, meters."""

LAYER_FRICTION_RADIUS = REPULSION_EPS + LAYER_FRICTION_MARGIN
"""Contact distance between layers at the default clearance, meters (5 mm): an outer vertex closer than this to its
inner partner, along the partner's normal at t+1. Wider than the body's 3 mm because the repulsion term holds
adjacent layers about its 3 mm clearance apart (:data:`smln.losses.repulsion.REPULSION_EPS`): a jacket resting on a
t-shirt sits there. With another clearance use :func:`layer_friction_radius`."""


def layer_friction_radius(repulsion_eps: float = REPULSION_EPS) -> float:
    """Contact distance between layers that goes with a repulsion clearance: ``repulsion_eps`` + 2 mm, meters.

    The repulsion loss holds a resting outer layer about ``repulsion_eps`` in front of the layer beneath, so the
    friction's contact band has to lie around that gap. A fixed 5 mm band with a 4.5 mm clearance (sessions 27-29)
    held fewer of a jacket's vertices: on 05_01_walk the share of jacket-shirt pairs within 5 mm was 0.17 for r36 A
    (4.5 mm clearance) against 0.23 for r27 (3 mm), within 3 mm 0.02 against 0.14, and r36 A's jacket sank 36.7 mm
    by frame 50 against r27's 30.8; continued with this radius it sank 33.1 mm (r37; docs/RESULTS.md, session 30).
    """
    return float(repulsion_eps) + LAYER_FRICTION_MARGIN


def layer_contact_slip(
    x_cur: torch.Tensor,
    x_next: torch.Tensor,
    normals_next: torch.Tensor,
    pairs: torch.Tensor,
    rest: ClothRest,
    radius: float = LAYER_FRICTION_RADIUS,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Tangential slip of each cross-layer pair over one step, whether the pair touches, and its gap.

    For pair (i outer, j inner): s = (x_i^{t+1} - x_i^t) - (x_j^{t+1} - x_j^t), minus its part along n_j (j's unit
    normal at t+1, a direction only: no gradient); the pair touches when (x_i - x_j) . n_j < ``radius`` at t+1
    and i is free (decided without gradient). Shared by :func:`layer_friction_energy` and
    :func:`smln.metrics.layer_slip`.

    Args:
        x_cur, x_next: (V, 3) cloth positions at t and t+1, meters (x_next may carry gradient).
        normals_next: (V, 3) unit cloth vertex normals at t+1.
        pairs: (P, 2) int64 (outer, inner) global vertex indices.
        rest: free mask.
        radius: contact distance, meters.

    Returns:
        (P, 3) tangential slip, meters; (P,) bool touching; (P,) signed gap d at t+1, meters (no gradient).
    """
    outer, inner = pairs[:, 0], pairs[:, 1]
    with torch.no_grad():
        n = normals_next.detach().index_select(0, inner)
        d = ((x_next.detach().index_select(0, outer) - x_next.detach().index_select(0, inner)) * n).sum(-1)
        touching = (d < radius) & (rest.free.index_select(0, outer) > 0)
    s = (x_next.index_select(0, outer) - x_cur.index_select(0, outer)) - (
        x_next.index_select(0, inner) - x_cur.index_select(0, inner))
    return s - (s * n).sum(-1, keepdim=True) * n, touching, d


def layer_friction_energy(
    x_cur: torch.Tensor,
    x_next: torch.Tensor,
    normals_next: torch.Tensor,
    pairs: torch.Tensor,
    rest: ClothRest,
    radius: float | None = None,
    g: float = GRAVITY,
    contact_stiffness: float = 0.0,
    eps: float = REPULSION_EPS,
) -> torch.Tensor:
    """Friction work of an outer garment layer sliding over the layer beneath during one step.

    The body term (:func:`friction_energy`) only holds the innermost layer: without this one a jacket lying on a
    t-shirt slides on it as on ice (the learned models let an open jacket sink off the shoulders over a walk
    3-4x faster than a physics simulator; at weight 1.5 this term did not measurably slow that after 24k
    fine-tuning steps, docs/RESULTS.md, session 11). Eq. 22 read for the layer beneath as the "adjacent face":
    for each cross-layer pair (i outer, j inner) from :func:`smln.losses.repulsion.layer_pairs`, in contact
    when d = (x_i - x_j) . n_j < ``radius`` at t+1
    (decided without gradient; a penetrated pair, d < 0, is in contact too; the radius follows the clearance,
    :func:`layer_friction_radius`):

        s = (x_i^{t+1} - x_i^t) - (x_j^{t+1} - x_j^t)          slip of i relative to its partner
        s^T = s - (s . n_j) n_j
        E = sum_{pairs in contact} mu m_i g * (sqrt(||s^T||^2 + c^2) - c)

    with the normal force N approximated by the outer vertex's weight (N = m_i g), as for the body. With
    ``contact_stiffness`` k > 0 (the repulsion loss's λr) the pair's contact force is added to it, lagged (no
    gradient) as in IPC's friction:

        N = m_i g + 3 k (eps - max(d, 0))_+^2          the push of k (eps - d)_+^3 (Eq. 25) at d, capped at d = 0
        E = sum_{pairs in contact} mu N (sqrt(||s^T||^2 + c^2) - c)

    The weight alone cannot hold a garment where it hangs: a jacket's shoulder vertices carry the weight of the
    panels below them through the fabric's tension, and press into the t-shirt with it. The cap keeps an
    interpenetrated pair (d < 0, a failure of the repulsion) from gluing the layers together.
    The gradient reaches both vertices (equal and opposite slip forces); pairs with a pinned outer vertex are
    left out.

    Args:
        x_cur, x_next: (V, 3) cloth positions at t and t+1, meters.
        normals_next: (V, 3) unit cloth vertex normals at t+1 (used as directions only, without gradient).
        pairs: (P, 2) int64 (outer, inner) global vertex indices.
        rest: masses, free mask, material (mu = ``rest.material.friction``).
        radius: contact distance, meters (None = :func:`layer_friction_radius` of ``eps``: 5 mm at the default
            3 mm clearance); g: m/s^2.
        contact_stiffness: k, J/m^3 (0 = the weight alone); eps: the repulsion clearance, meters.

    Returns:
        scalar energy, J (0 when there are no pairs).
    """
    if pairs.numel() == 0:
        return x_next.sum() * 0.0
    if radius is None:
        radius = layer_friction_radius(eps)
    st, touching, d = layer_contact_slip(x_cur, x_next, normals_next, pairs, rest, radius)
    with torch.no_grad():
        normal_force = g * rest.mass.index_select(0, pairs[:, 0])
        if contact_stiffness > 0:
            normal_force = normal_force + 3.0 * contact_stiffness * torch.clamp(eps - d.clamp(min=0.0), min=0.0) ** 2
        weight = rest.material.friction * normal_force * touching.to(x_next.dtype)
    c = SLIP_SMOOTHING
    slip = torch.sqrt((st * st).sum(-1) + c * c) - c
    return (weight * slip).sum()
