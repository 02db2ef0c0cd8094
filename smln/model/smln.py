"""SMLN: encoder -> hierarchical processor -> decoder (p) + repulsion layer (a) (paper §3.2-3.3, Eq. 9-16)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np
import torch
from torch import nn

from smln.cloth import DT, GRAVITY
from smln.geometry import PointTree, build_tree, nearest_vertices
from smln.geometry.surface import closest_surface_points
from smln.graph.hierarchy import check_rules
from smln.graph.multilayer import (
    BODY_EDGE_DIM,
    LEGACY_BODY_EDGE_DIM,
    MESH_EDGE_DIM,
    NODE_DIM,
    VIRTUAL_EDGE_DIM,
    GraphInputs,
    GraphTopology,
    vertex_normals,
)
from smln.model.mlp import MLP
from smln.model.normalizer import Normalizer
from smln.model.processor import Processor
from smln.model.repulsion import RepulsionLayer

REPULSION_PAIRINGS = ("vertex", "deeper", "nearest")
"""Values of :attr:`SMLNConfig.repulsion_pairing`."""

BODY_PAIRINGS = ("edge", "nearest", "edge_inside")
"""Values of :attr:`SMLNConfig.body_pairing`."""

WEIGHTLESS_FIELDS = ("repulsion_pairing", "body_pairing")
""":class:`SMLNConfig` fields that change how the weights are used, not which weights there are: a checkpoint's
weights load into a model that differs from its config only there (``smln train --init-from``)."""

BODY_REPULSION_MAX_DEPTH = 0.02
"""The body stage of the repulsion layer leaves garment vertices deeper than this behind their nearest body vertex's
normal plane alone, m (:data:`smln.projection.BODY_MAX_DEPTH`: deeper, the nearest-vertex test is mostly wrong)."""


@dataclass
class SMLNConfig:
    """Architecture of an SMLN model (everything a checkpoint needs to rebuild it).

    Defaults are chosen for the speed targets (<= 50 ms/frame for a 2-layer ~5k-vertex outfit on 2 CPU
    cores, <= 0.25 s per training step on a ~1.5k-vertex outfit). One message-passing step on the fine level
    of a 5k-vertex outfit costs ~20-30 ms at latent 64 (DESIGN.md "Speed facts"), so the fine level gets only
    one step on the way down and one on the way up (it must end at the fine level so the decoder sees sharp
    per-vertex information), and the remaining steps run on the anchor levels. Latent 64 (the paper's 128
    costs ~2.5x per step) and one hidden layer per MLP (the MLP class defaults to two, MeshGraphNets-style;
    the measured probe in DESIGN.md used one) keep the fine steps affordable.

    Anchor levels (measured on a 2-layer ~5k-vertex outfit, 30k fine mesh edges): one even-BFS pass keeps
    about HALF the nodes (not a quarter), and HOOD's two-hop rule densifies every level (mean degrees ~10, 17,
    30), so levels 1-3 carried 24k, 20k and 18k edges and dominated the network time (~204 ms/frame, 1
    thread). Joining anchors whose clusters touch (``coarse_edges="cluster"``) keeps degrees mesh-like (~6, 8,
    13 with the even-BFS anchors: about a third of the coarse edge cost). Re-applying the even-BFS pass to
    reach a quarter does not work (it keeps whole BFS rings; a 5k-vertex outfit collapsed to one node per
    component at level 3), so anchors are a maximal independent set of each level's graph
    (``anchors="mis"``): ~1/4 of the nodes per level (4820 -> 1141 -> 291 -> 83 on tshirt_jacket at 2 cm,
    mean degree ~5.5, edges 6.6k, 1.6k, 0.4k vs 28k fine), every level connected per component.
    ``coarse_edges="two_hop", anchors="bfs_even"`` is the earlier (HOOD) hierarchy; checkpoints saved before
    these fields existed were trained on it. See ``bench/rollout_speed.py`` for the figures.

    Attributes:
        latent_size: width of node/edge latents and MLP hidden layers.
        mlp_hidden_layers: hidden layers of every encoder/processor/decoder MLP.
        levels: anchor levels of the hierarchy (HOOD: 3).
        coarse_edges: anchor-level connectivity: ``"cluster"`` (anchors whose clusters touch, default) or
            ``"two_hop"`` (HOOD: kept nodes at most two hops apart); :mod:`smln.graph.hierarchy`.
        anchors: anchor choice per level: ``"mis"`` (maximal independent set, ~1/4 of the nodes, default)
            or ``"bfs_even"`` (HOOD: even BFS distance, ~1/2 of the nodes).
        schedule: ((level, steps), ...) visited in order; starts and ends at level 0, changes level by one.
        body_radius: body world edge radius, m (HOOD: 3 cm).
        body_normal_features: body world edges also carry the body vertex normal and the signed distance along
            it (13 columns instead of 9, :mod:`smln.graph.multilayer`). Cards written before this field existed
            load with False (:data:`smln.checkpoint.LEGACY_CONFIG`).
        virtual_radius: inter-layer virtual edge radius, m.
        use_repulsion_layer: add the repulsion layer's acceleration ``a`` (Eq. 14-16).
        body_repulsion: the repulsion layer also gets a stage between the body and the garments, run before the
            layer pairs (an extension of the paper, whose layer acts between garment layers only): every garment
            vertex with a body world edge is an outer vertex and its nearest body vertex (at t+1, with the body's
            vertex normal) the inner one, with its own MLP (same form, Eq. 14-15) and
            ``body_repulsion_threshold``; pairs deeper than :data:`BODY_REPULSION_MAX_DEPTH` are left alone.
            Needs ``use_repulsion_layer`` and ``body_normal_features``. Cards written before this field existed
            load with False.
        body_repulsion_threshold: the body stage's activation distance along the body normal, m.
        repulsion_threshold: repulsion activation distance along the inner normal, m.
        repulsion_hidden: repulsion MLP width (paper: 32).
        repulsion_pairing: how the layer reads an outer vertex against the layer beneath. ``"vertex"`` (paper
            Eq. 14): its nearest inner vertex of step t (the virtual edge) and that vertex's normal at x̂.
            ``"deeper"`` (our extension): also the closest point of the inner layer's *triangles* at step t,
            carried to x̂ by its barycentric weights, with the interpolated vertex normal; whichever of the two
            reads the vertex deeper (smaller E_r) is the pair that pushes it. A closest point on the inner
            layer's hem is no surface reading (the vertex lies beyond the hem), nor is one on a degenerate
            (zero-area) triangle, nor one whose normal faces
            away from the nearest inner vertex's (the back of a fold: its reading would push the vertex inward,
            toward the body). The vertex reading alone misses an outer vertex that sits in front of its nearest
            inner vertex's tangent plane but behind the inner surface between vertices (a fold, a concave patch;
            the point-to-triangle L-Coll). The same weights serve both (the MLP's inputs have the same meaning).
            Costs a closest-point query per layer pair and step (~1.2x per frame at 2 cm, bench/rollout_speed.py).
            ``"nearest"`` (our extension, session 41): the same outer vertices (those with a virtual edge at step
            t), each against the inner vertex nearest to its prediction at t+1 (the layer beneath taken where its
            own push left it) and that vertex's normal there: the pairing of the L-Coll metric, which reads the
            final positions (:func:`nearest_layer_pairs`; a KD-tree over the inner layer per stage and step).
            Cards written before this field existed load with ``"vertex"``.
        body_pairing: which body vertex the body stage reads a garment vertex against. ``"edge"`` (as every stage
            was trained): its body world edge's, the body vertex nearest to it at step t. ``"nearest"`` (our
            extension, session 40): the body vertex nearest to its prediction x̂ at t+1 (within ``body_radius``,
            every garment vertex, with or without a world edge), the pairing of the H-Coll metric and of the body
            collision loss. On the shipped model about 60 % of the garment vertices the H-Coll metric finds inside
            the body at t+1 are read *outside* by their world edge's vertex (fast limbs: the nearest body vertex
            changed within the frame), so the stage does not push them. The same weights serve both. Costs a
            KD-tree over the body at t+1 per step. ``"edge_inside"`` (our extension, session 42): the edge pairs'
            push as trained, then a second pass of the same MLP for the garment vertices that push leaves *inside*
            the body vertex nearest to them (signed distance < 0 along its normal at t+1), read against that vertex
            (:func:`inside_body_pairs`): the vertices the H-Coll metric counts, and no others, get the nearest
            reading, so the push the network was trained with stays where the edge reading gave it.
            Cards written before this field existed load with ``"edge"``.
        output_scale: ONE isotropic scale of the decoder output, m/frame^2 (g·Δt² ≈ 1.1 cm/frame²); per-axis
            output statistics from near-rigid motion have ~0 vertical variance and would freeze Z.
        normalizer_accumulations: training forward calls that update the input statistics, then frozen.
        dt: time step the graph features carry, s.
    """

    latent_size: int = 64
    mlp_hidden_layers: int = 1
    levels: int = 3
    coarse_edges: str = "cluster"
    anchors: str = "mis"
    schedule: tuple[tuple[int, int], ...] = field(
        default_factory=lambda: ((0, 1), (1, 1), (2, 1), (3, 2), (2, 1), (1, 1), (0, 1))
    )
    body_radius: float = 0.03
    body_normal_features: bool = True
    virtual_radius: float = 0.05
    use_repulsion_layer: bool = True
    repulsion_threshold: float = 0.005
    repulsion_hidden: int = 32
    repulsion_pairing: str = "vertex"
    body_repulsion: bool = False
    body_repulsion_threshold: float = 0.003
    body_pairing: str = "edge"
    output_scale: float = GRAVITY * DT * DT
    normalizer_accumulations: int = 200
    dt: float = DT

    def __post_init__(self) -> None:
        check_rules(self.coarse_edges, self.anchors)
        self.schedule = tuple((int(lv), int(n)) for lv, n in self.schedule)
        if not self.schedule or self.schedule[0][0] != 0 or self.schedule[-1][0] != 0:
            raise ValueError("schedule must start and end at level 0")
        for (a, _), (b, _) in zip(self.schedule[:-1], self.schedule[1:], strict=True):
            if abs(a - b) != 1:
                raise ValueError(f"schedule levels must change by exactly one, got {a} -> {b}")
        if max(lv for lv, _ in self.schedule) > self.levels:
            raise ValueError("schedule visits a level above `levels`")
        if self.body_repulsion and not (self.use_repulsion_layer and self.body_normal_features):
            raise ValueError("body_repulsion needs use_repulsion_layer and body_normal_features")
        if self.repulsion_pairing not in REPULSION_PAIRINGS:
            raise ValueError(f"repulsion_pairing must be one of {REPULSION_PAIRINGS}, got {self.repulsion_pairing!r}")
        if self.body_pairing not in BODY_PAIRINGS:
            raise ValueError(f"body_pairing must be one of {BODY_PAIRINGS}, got {self.body_pairing!r}")
        if not self.body_repulsion_threshold > 0:
            raise ValueError(f"body_repulsion_threshold must be > 0 m, got {self.body_repulsion_threshold}")

    @property
    def body_edge_dim(self) -> int:
        """Columns of the body world edge features (13 with body normals, 9 without)."""
        return BODY_EDGE_DIM if self.body_normal_features else LEGACY_BODY_EDGE_DIM

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict (schedule as nested lists)."""
        d = asdict(self)
        d["schedule"] = [list(s) for s in self.schedule]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SMLNConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``TypeError``."""
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise TypeError(f"unknown SMLNConfig fields: {sorted(unknown)}")
        return cls(**d)


def nearest_body_pairs(graph: GraphInputs, x_hat: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Each garment vertex with the body vertex nearest to its prediction x̂ at t+1, if closer than ``radius``.

    The pairing of ``SMLNConfig.body_pairing = "nearest"`` (and of the H-Coll metric and the body collision loss).
    Rows of x̂ that are not finite are left out.

    Args:
        graph: the step's inputs; ``body_cur``, ``body_next`` and ``body_normals_next`` must be set
            (:meth:`GraphTopology.build` sets them for a topology with body normals).
        x_hat: (V, 3) predicted positions at t+1, m.
        radius: the largest distance of a pair, m.

    Returns:
        q (P,) int64 garment vertices and r (P,) int64 their body vertices, on x̂'s device.
    """
    if graph.body_next is None or graph.body_cur is None or graph.body_normals_next is None:
        raise ValueError("body_pairing 'nearest' needs the body at t and t+1 and its normals at t+1 in the graph "
                         "inputs (GraphTopology.build with body normals)")
    xh = x_hat.detach()
    ok = torch.isfinite(xh).all(dim=-1)
    rows = torch.nonzero(ok, as_tuple=True)[0]
    if rows.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=x_hat.device)
        return empty, empty
    tree = graph.body_tree_next if graph.body_tree_next is not None else build_tree(graph.body_next.detach())
    idx, dist = nearest_vertices(xh.index_select(0, rows), tree=tree)
    keep = dist.to(x_hat.device) < radius
    return rows[keep], idx.to(x_hat.device)[keep]


def inside_body_pairs(graph: GraphInputs, x: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The garment vertices inside the body at t+1: each with its nearest body vertex (within ``radius``) when it
    lies behind that vertex's tangent plane (the H-Coll metric's test).

    The second pass of ``SMLNConfig.body_pairing = "edge_inside"``.

    Args:
        graph: the step's inputs (``body_next`` and ``body_normals_next`` set, as for :func:`nearest_body_pairs`).
        x: (V, 3) garment positions at t+1 so far (x̂ plus the edge pairs' push), m.
        radius: the largest distance of a pair, m.

    Returns:
        q (P,) int64 garment vertices and r (P,) int64 their nearest body vertices, P <= V.
    """
    q, r = nearest_body_pairs(graph, x, radius)
    depth = ((x.detach().index_select(0, q) - graph.body_next.index_select(0, r))
             * graph.body_normals_next.index_select(0, r)).sum(-1)
    inside = depth < 0.0
    return q[inside], r[inside]


def nearest_layer_pairs(topology: GraphTopology, x_k: torch.Tensor, outer: torch.Tensor, inner_layer: int,
                        ) -> torch.Tensor:
    """Each outer vertex with the vertex of the layer beneath nearest to it at the predicted positions.

    The pairing of ``SMLNConfig.repulsion_pairing = "nearest"`` (and of the L-Coll metric, which reads each outer
    vertex against its nearest inner vertex at the frame's final positions). Rows of ``x_k`` that are not finite
    (an outer vertex, or an inner vertex, with a NaN prediction) are left out.

    Args:
        topology: the outfit's topology (``layer_slices``).
        x_k: (V, 3) predicted positions, m: x̂ plus the pushes of the stages so far (the inner layer is final).
        outer: (P,) int64 the stage's outer vertices (global indices; unique).
        inner_layer: the layer beneath them.

    Returns:
        (2, P') int64 pairs (outer i, its nearest inner vertex j at ``x_k``), P' <= P, on ``x_k``'s device.
    """
    dev = x_k.device
    sl = topology.layer_slices[inner_layer]
    xk = x_k.detach()
    inner = torch.arange(sl.start, sl.stop, device=dev)
    inner = inner[torch.isfinite(xk.index_select(0, inner)).all(dim=-1)]
    outer = outer[torch.isfinite(xk.index_select(0, outer)).all(dim=-1)]
    if inner.numel() == 0 or outer.numel() == 0:
        return torch.zeros((2, 0), dtype=torch.long, device=dev)
    idx, _ = nearest_vertices(xk.index_select(0, outer), xk.index_select(0, inner))
    return torch.stack([outer, inner[idx.to(dev)]])


def surface_partners(topology: GraphTopology, x_cur: torch.Tensor, x_k: torch.Tensor, n_k: torch.Tensor,
                     outer: torch.Tensor, inner_layer: int,
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each outer vertex's closest point on the inner layer's triangles at step t, carried to ``x_k``.

    Args:
        x_cur: (V, 3) positions at t, m. x_k: (V, 3) predicted positions, m. n_k: (V, 3) unit vertex normals at
            ``x_k``. outer: (P,) int64 vertices queried. inner_layer: the layer whose triangles are searched.

    Returns:
        c_cur (P, 3) the point at t, c_next (P, 3) the same barycentric point at ``x_k`` (differentiable), n_c (P, 3)
        the interpolated unit normal there, and readable (P,) bool: a valid closest point off the inner layer's
        hem (elsewhere the rows are finite but mean nothing).
    """
    faces, boundary = topology.layer_surface(inner_layer)
    x_np = x_cur.detach().cpu().numpy()
    sp = closest_surface_points(x_np[outer.cpu().numpy()], x_np, faces, boundary)
    corners = torch.as_tensor(sp.corners, device=x_k.device)
    w = torch.as_tensor(sp.bary, dtype=x_k.dtype, device=x_k.device).unsqueeze(-1)
    c_cur = (w * x_cur[corners]).sum(1)
    c_next = (w * x_k[corners]).sum(1)
    n_c = nn.functional.normalize((w * n_k[corners]).sum(1), dim=-1)
    return c_cur, c_next, n_c, torch.as_tensor(sp.valid & ~sp.on_boundary, device=x_k.device)


class SMLN(nn.Module):
    """The SMLN network. Per step: ``p, a, extras = model(topology.build(...))``.

    Outfit-independent: all weights and normaliser buffers have shapes fixed by the config, so one model
    animates any outfit (the topology is built per outfit by :meth:`make_topology`).
    """

    def __init__(self, config: SMLNConfig | None = None) -> None:
        super().__init__()
        cfg = config or SMLNConfig()
        self.config = cfg
        lat, nh, acc = cfg.latent_size, cfg.mlp_hidden_layers, cfg.normalizer_accumulations
        self.node_norm = Normalizer(NODE_DIM, acc)
        self.mesh_norm = Normalizer(MESH_EDGE_DIM, acc)
        self.virtual_norm = Normalizer(VIRTUAL_EDGE_DIM, acc)
        self.body_norm = Normalizer(cfg.body_edge_dim, acc)
        self.coarse_norm = nn.ModuleList([Normalizer(MESH_EDGE_DIM, acc) for _ in range(cfg.levels)])
        self.node_encoder = MLP(NODE_DIM, lat, lat, nh)  # Eq. 9
        self.mesh_encoder = MLP(MESH_EDGE_DIM, lat, lat, nh)  # Eq. 10
        self.virtual_encoder = MLP(VIRTUAL_EDGE_DIM, lat, lat, nh)  # Eq. 11
        self.body_encoder = MLP(cfg.body_edge_dim, lat, lat, nh)  # Eq. 12
        self.coarse_encoders = nn.ModuleList([MLP(MESH_EDGE_DIM, lat, lat, nh) for _ in range(cfg.levels)])
        self.processor = Processor(lat, cfg.schedule, nh)
        self.decoder = MLP(lat, 3, lat, nh, layer_norm=False)
        with torch.no_grad():  # start close to inertial motion rather than O(g dt^2) noise per vertex
            self.decoder[-1].weight.mul_(0.01)
            self.decoder[-1].bias.zero_()
        self.repulsion = RepulsionLayer(cfg.repulsion_threshold, cfg.repulsion_hidden)
        if cfg.body_repulsion:
            self.body_repulsion = RepulsionLayer(cfg.body_repulsion_threshold, cfg.repulsion_hidden,
                                                 max_depth=BODY_REPULSION_MAX_DEPTH)
            self.body_repulsion.init_as_projection()
        self.register_buffer("output_scale", torch.tensor(float(cfg.output_scale), dtype=torch.float32))

    def make_topology(self, cloth: Any) -> GraphTopology:
        """Static graph of an outfit with this model's radii and levels."""
        c = self.config
        return GraphTopology.from_cloth(
            cloth, levels=c.levels, coarse_edges=c.coarse_edges, anchors=c.anchors,
            body_radius=c.body_radius, virtual_radius=c.virtual_radius, dt=c.dt,
            body_normals=c.body_normal_features,
        )

    def forward(self, graph: GraphInputs, topology: GraphTopology) -> tuple[
        torch.Tensor, torch.Tensor, dict[str, Any]
    ]:
        """One step.

        Args:
            graph: features of the step (:meth:`GraphTopology.build`).
            topology: the outfit's static topology (hierarchy, faces, pinned mask).

        Returns:
            p: (V, 3) predicted acceleration, m/frame^2 (zero on pinned vertices).
            a: (V, 3) repulsion acceleration, m/frame^2 (zeros if the layer is off; zero on pinned vertices): the
                body stage's push (if ``body_repulsion``) plus the layer pairs'.
            extras: ``x_hat`` (V, 3) = x_t + v_t + p, ``x_next`` = x_hat + a with pinned vertices at their
                targets, ``repulsion`` (the layer's extras, if on), ``body_repulsion`` (the body stage's: ``a``
                (V, 3), ``active_vertices`` (P_a,) the garment vertices pushed, ``magnitude`` (P_a,) m/frame^2,
                ``signed_distance`` (P,) of every pair's garment vertex at x̂, m: one per body edge, or per
                nearest pair; with ``"edge_inside"`` the edge pairs', and ``active_vertices`` / ``magnitude`` of
                both passes, a vertex pushed in both listed twice)
        """
        h = self.node_encoder(self.node_norm(graph.node_features))
        me, ve = graph.mesh_edges, graph.virtual_edges
        fine = {
            "mesh": (me[0], me[1], self.mesh_encoder(self.mesh_norm(graph.mesh_features))),
            "virtual": (ve[0], ve[1], self.virtual_encoder(self.virtual_norm(graph.virtual_features))),
            "body": (None, graph.body_receivers, self.body_encoder(self.body_norm(graph.body_features))),
        }
        visited = {lv for lv, _ in self.config.schedule}
        coarse = []
        for k, feat in enumerate(graph.coarse_features):
            ed = topology.level_edges[k]
            if k + 1 in visited:  # levels the schedule never visits (pooled through only) need no edges
                coarse.append((ed[0], ed[1], self.coarse_encoders[k](self.coarse_norm[k](feat))))
            else:
                coarse.append((ed[0], ed[1], feat[:, :0]))
        h = self.processor(
            h, fine, coarse, topology.level_parent, topology.level_sizes, topology.level_inv_count
        )
        free = topology.free.unsqueeze(-1).to(h.dtype)
        p = self.decoder(h) * self.output_scale * free
        x_hat = graph.x_cur + graph.velocity + p
        extras: dict[str, Any] = {}
        if self.config.use_repulsion_layer:
            a_body = self._body_repulsion(graph, x_hat, free, extras) if self.config.body_repulsion else None
            a, extras["repulsion"] = self._cascade_repulsion(topology, graph, x_hat, free, a_body)
        else:
            a = torch.zeros_like(p)
        pin = topology.pinned.unsqueeze(-1)
        x_next = torch.where(pin, graph.pinned_next, x_hat + a)
        extras["x_hat"] = x_hat
        extras["x_next"] = x_next
        return p, a, extras

    def _body_repulsion(self, graph: GraphInputs, x_hat: torch.Tensor, free: torch.Tensor,
                        extras: dict[str, Any]) -> torch.Tensor:
        """The body stage: a push along the body normal for garment vertices close to or inside the body.

        With ``body_pairing "edge"`` the pairs are the body world edges (garment vertex q, its nearest body vertex r
        at t), and the body's positions and normal come from the edge features: ``d0 = x_q - b_r(t)``,
        ``d1 = x_q - b_r(t+1)`` and the unit normal ``n_r(t+1)`` (columns 0-2, 4-6 and 9-11,
        :meth:`GraphTopology.build`), so b_r(t) = x_q - d0 and b_r(t+1) = x_q - d1. With ``"nearest"`` they are each
        garment vertex within ``body_radius`` of the body at t+1 and the body vertex nearest to its x̂
        (:func:`nearest_body_pairs`), read from the body positions and normals the graph inputs carry. With
        ``"edge_inside"`` the edge pairs push first, then the vertices still inside the body are read against their
        nearest body vertex (:func:`inside_body_pairs`) in a second pass of the same MLP. The body is kinematic and
        is not pushed.

        Returns:
            (V, 3) m/frame^2, zero on pinned vertices; stores the stage's extras in ``extras["body_repulsion"]``.
        """
        if self.config.body_pairing == "nearest":
            q, r = nearest_body_pairs(graph, x_hat, self.config.body_radius)
            a, ex = self._push_against_body(graph, x_hat, q, r)
        else:
            q, f = graph.body_receivers, graph.body_features
            xq = graph.x_cur.index_select(0, q)
            a, ex = self.body_repulsion.push(q, xq, x_hat.index_select(0, q), xq - f[:, 0:3], xq - f[:, 4:7],
                                             f[:, 9:12], x_hat.shape[0])
        a = a * free
        ex["active_vertices"] = q[ex.pop("active")]
        if self.config.body_pairing == "edge_inside":
            x_edge = x_hat + a  # where the edge pairs' push leaves each vertex
            q2, r2 = inside_body_pairs(graph, x_edge, self.config.body_radius)
            a2, ex2 = self._push_against_body(graph, x_edge, q2, r2)
            a = a + a2 * free
            ex["active_vertices"] = torch.cat([ex["active_vertices"], q2[ex2["active"]]])
            ex["magnitude"] = torch.cat([ex["magnitude"], ex2["magnitude"]])
        extras["body_repulsion"] = {"a": a, **ex}
        return a

    def _push_against_body(self, graph: GraphInputs, x: torch.Tensor, q: torch.Tensor, r: torch.Tensor,
                           ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The body stage's push of garment vertices ``q`` (P,) at positions ``x`` (V, 3, m) read against body
        vertices ``r`` (P,) from the body positions and normals the graph inputs carry (:meth:`RepulsionLayer.push`).
        """
        return self.body_repulsion.push(q, graph.x_cur.index_select(0, q), x.index_select(0, q),
                                        graph.body_cur.index_select(0, r), graph.body_next.index_select(0, r),
                                        graph.body_normals_next.index_select(0, r), x.shape[0])

    def _cascade_repulsion(
        self, topology: GraphTopology, graph: Any, x_hat: torch.Tensor, free: torch.Tensor,
        a_start: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The repulsion layer applied layer pair by layer pair, inner pairs first (Eq. 14-16).

        With two layers this is one call of :class:`RepulsionLayer` on all pairs. With more, the pairs whose outer
        vertex is in layer k are processed after x̂ of layer k-1 has received its own push, against the normals at
        that updated x̂: a middle layer pushed out of the innermost one is then seen where it went by the layer
        above it. Applied all at once, the jacket of a 3-layer outfit could not react to the push its neighbour
        got in the same step, and the push moved the middle layer *into* the jacket (test clips, seen 3-layer
        outfit: middle-vs-inner L-Coll 2.3 %, outer-vs-middle 8.0 %; docs/RESULTS.md).

        ``a_start``: (V, 3) the body stage's push, applied before the first layer pair (None: zeros).

        Returns:
            a (V, 3) m/frame^2 (zero on pinned vertices; includes ``a_start``) and the layer's extras, concatenated
            over the stages.
        """
        pairs = graph.repulsion_pairs
        outer_layer = topology.layer_index.to(pairs.device)[pairs[0]]
        a = torch.zeros_like(x_hat) if a_start is None else a_start
        stages: list[dict[str, torch.Tensor]] = []
        for k in range(1, max(topology.num_layers, 2)):  # one stage per adjacent layer pair (1-2 in practice)
            x_k = x_hat + a
            n_k = vertex_normals(x_k, topology.faces)
            stage = pairs[:, outer_layer == k]
            if self.config.repulsion_pairing == "nearest" and stage.shape[1] > 0:
                stage = nearest_layer_pairs(topology, x_k, stage[0], k - 1)
            if self.config.repulsion_pairing == "deeper" and stage.shape[1] > 0:
                a_k, rep = self._push_deeper(topology, graph.x_cur, x_k, n_k, stage, k - 1)
            else:
                a_k, rep = self.repulsion(graph.x_cur, x_k, n_k, stage)
            a = a + a_k * free
            stages.append(rep)
        return a, {key: torch.cat([r[key] for r in stages], dim=-1) for key in stages[0]}

    def _push_deeper(self, topology: GraphTopology, x_cur: torch.Tensor, x_k: torch.Tensor, n_k: torch.Tensor,
                     stage: torch.Tensor, inner_layer: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One stage with ``repulsion_pairing="deeper"``: each pair (outer i, nearest inner vertex j) is read
        against j and against the closest point c of the inner layer's triangles at step t; the deeper reading
        pushes.

        Args:
            x_cur: (V, 3) positions at t, m. x_k: (V, 3) predicted positions so far, m. n_k: (V, 3) unit
                vertex normals at ``x_k``. stage: (2, P) the stage's pairs (outer i, inner j), P >= 1.
            inner_layer: the layer beneath the stage's outer vertices.

        Returns:
            as :meth:`RepulsionLayer.forward` (``active_pairs`` names j also where the surface point pushed).
        """
        i, j = stage[0], stage[1]
        c_cur, c_next, n_c, readable = surface_partners(topology, x_cur, x_k, n_k, i, inner_layer)
        e_surface = ((x_k[i] - c_next) * n_c).sum(-1)
        e_vertex = ((x_k[i] - x_k[j]) * n_k[j]).sum(-1)
        facing = (n_c * n_k[j]).sum(-1) > 0.0
        use = readable & (e_surface < e_vertex) & facing
        use = use.unsqueeze(-1)
        inner_cur = torch.where(use, c_cur, x_cur[j])
        inner_next = torch.where(use, c_next, x_k[j])
        normal = torch.where(use, n_c, n_k[j])
        a, ex = self.repulsion.push(i, x_cur[i], x_k[i], inner_cur, inner_next, normal, x_k.shape[0])
        ex["active_pairs"] = torch.stack([i[ex["active"]], j[ex["active"]]])
        del ex["active"]
        return a, ex

    def step(
        self,
        topology: GraphTopology,
        x_prev: torch.Tensor,
        x_cur: torch.Tensor,
        body_cur: torch.Tensor,
        body_next: torch.Tensor,
        pinned_next: torch.Tensor | None = None,
        body_tree: PointTree | None = None,
        body_nearest: tuple[np.ndarray, np.ndarray] | None = None,
        body_normals_next: torch.Tensor | None = None,
        body_tree_next: PointTree | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
        """Build the step's graph and run :meth:`forward` (see :meth:`GraphTopology.build` for the args)."""
        graph = topology.build(x_prev, x_cur, body_cur, body_next, pinned_next, body_tree=body_tree,
                               body_nearest=body_nearest, body_normals_next=body_normals_next,
                               body_tree_next=body_tree_next)
        p, a, extras = self(graph, topology)
        extras["graph"] = graph
        return p, a, extras
