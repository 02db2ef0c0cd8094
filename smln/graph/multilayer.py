"""The multi-layer garment graph (paper §3.1, Eq. 1-8): static per-outfit topology and the per-step build.

:class:`GraphTopology` holds what never changes for an outfit (mesh edges of every layer in both directions,
rest edge vectors, node types, the anchor hierarchy); :meth:`GraphTopology.build` turns the state at one step
into :class:`GraphInputs` (features of every node and edge set plus the proximity edges of that step).

Feature sets (all translation invariant: only differences of positions, normals, velocities and constants):

- node (24, :data:`NODE_FEATURES`): velocity v_t = x_t - x_{t-1} (3, Eq. 2), vertex normal at x_t (3, the
  position-derived feature of Eq. 4), known next displacement of pinned vertices x_{t+1} - x_t (3, zero for
  free vertices), node type one-hot free/pinned (2), hierarchy-level one-hot (4: the coarsest anchor level
  the node belongs to), layer position k/(L-1) and outermost flag (2), Δt (1), log10 mass (1, Eq. 3), friction
  μ (1, Eq. 4), material (3, :meth:`~smln.cloth.Material.as_features`), body-contact flag (1: has a body edge).
- mesh edge (12): x_s - x_r (3), norm, rest x_s - x_r (3), norm, Δt, material (3). The same set on the coarse
  anchor levels (between anchors).
- virtual inter-layer edge (9, Eq. 5-6): x_s - x_r at t (3), norm, difference of the inertial predictions
  x̂ = x_t + v_t (3), norm, Δt. Each vertex of layer k+1 receives from its nearest vertex of layer k within
  ``virtual_radius`` and vice versa.
- body world edge (13, Eq. 7-8): x_cloth(t) - x_body(t) (3), norm, x_cloth(t) - x_body(t+1) (3), norm, Δt, and
  (our addition) the body vertex's outward unit normal at t+1 (3) with the signed distance
  (x_cloth(t) - x_body(t+1)) · n (1, negative inside the body). Each garment vertex receives from its nearest body
  vertex (at t) within ``body_radius``. Body vertices are not graph nodes here (HOOD makes them nodes, whose
  normals then reach the cloth through the messages), so without the normal columns a body edge cannot tell a
  vertex 5 mm outside the skin from one 5 mm inside it. Models built with ``body_normals=False`` (checkpoints
  saved before session 5) use the first 9 columns only (:data:`LEGACY_BODY_EDGE_DIM`).

Edge arrays are (2, E) with row 0 = sender, row 1 = receiver. Virtual edges whose receiver lies in the upper
layer of the pair are also the repulsion layer's pairs (outer vertex i, nearest inner vertex j).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smln.cloth import DT, Cloth
from smln.geometry import PointTree, build_tree, vertex_normals
from smln.geometry.surface import boundary_edge_keys
from smln.graph.hierarchy import HierarchyLevel, anchor_hierarchy, finest_level_of, mesh_edges

NODE_FEATURES: tuple[tuple[str, int], ...] = (
    ("velocity", 3),
    ("normal", 3),
    ("pinned_next_displacement", 3),
    ("node_type", 2),
    ("hierarchy_level", 4),
    ("layer_position", 2),
    ("dt", 1),
    ("log_mass", 1),
    ("friction", 1),
    ("material", 3),
    ("body_contact", 1),
)
NODE_DIM = sum(n for _, n in NODE_FEATURES)  # 24
MESH_EDGE_DIM = 12
VIRTUAL_EDGE_DIM = 9
BODY_EDGE_DIM = 13
LEGACY_BODY_EDGE_DIM = 9


def _nearest(
    query: np.ndarray, ref: np.ndarray | None, radius: float, tree: PointTree | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest ``ref`` vertex of every ``query`` point within ``radius`` (a :class:`~smln.geometry.PointTree`).

    A radius-limited query (``smln.geometry.nearest_vertices`` has no radius cut, which the edge sets need).
    ``tree``: a prebuilt tree over ``ref`` (:func:`smln.geometry.build_tree`, the same tree as built here).

    Returns:
        query_idx (M,), ref_idx (M,) int64 for the M queries that found a neighbour.
    """
    if (tree.n if tree is not None else len(ref)) == 0 or len(query) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if tree is None:
        tree = build_tree(ref)
    dist, idx = tree.query(query, k=1, distance_upper_bound=radius)
    ok = np.isfinite(dist)
    return np.flatnonzero(ok).astype(np.int64), idx[ok].astype(np.int64)


@dataclass
class GraphInputs:
    """Everything the network needs at one step (torch tensors on the topology's device).

    Attributes:
        node_features: (V, 24).
        mesh_edges: (2, Em) sender/receiver of the fine mesh edges.
        mesh_features: (Em, 12).
        coarse_features: per anchor level, (E_k, 12) features of that level's edges.
        virtual_edges: (2, Ev) sender/receiver of the inter-layer edges.
        virtual_features: (Ev, 9).
        body_receivers: (Eb,) garment vertex of each body edge.
        body_features: (Eb, 13), or (Eb, 9) for a topology built with ``body_normals=False``.
        repulsion_pairs: (2, Er) (outer i, inner j): virtual edges whose receiver is in the upper layer.
        x_cur: (V, 3) positions at t.
        velocity: (V, 3) v_t = x_t - x_{t-1}.
        pinned_next: (V, 3) next positions of pinned vertices (rows of free vertices unused).
        body_cur, body_next: (Vb, 3) body vertices at t and t+1, m (what the body stage of the repulsion layer
            reads with ``SMLNConfig.body_pairing = "nearest"``); None for inputs built by hand.
        body_normals_next: (Vb, 3) unit outward body vertex normals at t+1, or None (a topology without body normals).
        body_tree_next: a KD-tree over ``body_next`` if the caller had one (the body stage's nearest pairing reuses
            it), else None.
    """

    node_features: torch.Tensor
    mesh_edges: torch.Tensor
    mesh_features: torch.Tensor
    coarse_features: list[torch.Tensor]
    virtual_edges: torch.Tensor
    virtual_features: torch.Tensor
    body_receivers: torch.Tensor
    body_features: torch.Tensor
    repulsion_pairs: torch.Tensor
    x_cur: torch.Tensor
    velocity: torch.Tensor
    pinned_next: torch.Tensor
    body_cur: torch.Tensor | None = None
    body_next: torch.Tensor | None = None
    body_normals_next: torch.Tensor | None = None
    body_tree_next: PointTree | None = None


class GraphTopology:
    """Static topology of one outfit: build once with :meth:`from_cloth`, then call :meth:`build` per step."""

    def __init__(
        self,
        cloth: Cloth,
        levels: list[HierarchyLevel],
        mesh_edge_index: torch.Tensor,
        *,
        body_radius: float,
        virtual_radius: float,
        dt: float,
        body_normals: bool = True,
    ) -> None:
        dev = cloth.rest_vertices.device
        self.cloth = cloth
        self.device = dev
        self.faces = cloth.faces.to(torch.int64)
        self.num_vertices = cloth.num_vertices
        self.num_layers = cloth.num_layers
        self.layer_slices = cloth.layer_slices()
        self.layer_index = cloth.layer_index.to(torch.int64)
        self.pinned = cloth.pinned.to(torch.bool)
        self.free = ~self.pinned
        self.body_radius = float(body_radius)
        self.virtual_radius = float(virtual_radius)
        self.dt = float(dt)
        self.body_normals = bool(body_normals)
        self.levels = levels
        self.mesh_edges = mesh_edge_index
        rest = cloth.rest_vertices.to(torch.float32)
        self.rest_vectors = rest[mesh_edge_index[0]] - rest[mesh_edge_index[1]]
        self.level_nodes = [torch.as_tensor(lv.nodes, device=dev) for lv in levels]
        self.level_edges = [torch.as_tensor(lv.edges, device=dev) for lv in levels]
        self.level_parent = [torch.as_tensor(lv.parent, device=dev) for lv in levels]
        # per-step constants, computed once: level sizes (no .item() in pooling), 1/cluster size for mean
        # pooling, anchor edges as fine-mesh indices, and the static columns of every edge feature set
        self.level_sizes = [lv.num_nodes for lv in levels]
        self.level_inv_count = []
        for par, size in zip(self.level_parent, self.level_sizes, strict=True):
            cnt = torch.bincount(par, minlength=size).to(torch.float32).clamp_min(1.0)
            self.level_inv_count.append((1.0 / cnt).unsqueeze(-1))
        self.level_global_edges = [nodes[edges] for nodes, edges in zip(self.level_nodes, self.level_edges,
                                                                          strict=True)]
        self.level_rest_vectors = [rest[g[0]] - rest[g[1]] for g in self.level_global_edges]
        self.material = cloth.material.as_features().to(dev)
        self.mesh_static = self._edge_static(self.rest_vectors)
        self.level_static = [self._edge_static(r) for r in self.level_rest_vectors]
        self.static_node = self._static_node_features()
        self._layer_surfaces: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def layer_surface(self, layer: int) -> tuple[np.ndarray, np.ndarray]:
        """Layer ``layer``'s triangles, (F_k, 3) int64 numpy rows into all V vertices, and the keys of their open
        boundary (:func:`smln.geometry.surface.boundary_edge_keys`); computed once per layer."""
        if layer not in self._layer_surfaces:
            faces = self.faces.cpu().numpy()
            faces = np.ascontiguousarray(faces[self.layer_index.cpu().numpy()[faces[:, 0]] == layer])
            self._layer_surfaces[layer] = (faces, boundary_edge_keys(faces, self.num_vertices))
        return self._layer_surfaces[layer]

    @classmethod
    def from_cloth(
        cls,
        cloth: Cloth,
        *,
        levels: int = 3,
        coarse_edges: str = "cluster",
        anchors: str = "mis",
        body_radius: float = 0.03,
        virtual_radius: float = 0.05,
        dt: float = DT,
        body_normals: bool = True,
    ) -> GraphTopology:
        """Static graph of an outfit.

        Args:
            cloth: the concatenated layers.
            levels: number of anchor levels (the hierarchy is cached per topology).
            coarse_edges: anchor connectivity, ``"cluster"`` or ``"two_hop"`` (:mod:`smln.graph.hierarchy`).
            anchors: anchor choice, ``"mis"`` or ``"bfs_even"`` (:mod:`smln.graph.hierarchy`).
            body_radius: max distance of a body world edge, m (HOOD: 3 cm).
            virtual_radius: max distance of an inter-layer virtual edge, m.
            dt: time step, s.
            body_normals: body edges carry the body normal and the signed distance (13 columns, default) or
                not (9 columns, checkpoints saved before session 5).
        """
        faces = cloth.faces.detach().cpu().numpy()
        e = mesh_edges(faces)
        lv = anchor_hierarchy(e, cloth.num_vertices, levels, rule=coarse_edges, anchors=anchors)
        edge_index = torch.as_tensor(e, device=cloth.rest_vertices.device)
        return cls(cloth, lv, edge_index, body_radius=body_radius, virtual_radius=virtual_radius, dt=dt,
                   body_normals=body_normals)

    def _edge_static(self, rest: torch.Tensor) -> torch.Tensor:
        """(E, 8) static columns of the mesh-edge features: rest vector, its norm, Δt, material."""
        n = rest.shape[0]
        return torch.cat(
            [rest, rest.norm(dim=-1, keepdim=True), torch.full((n, 1), self.dt, device=self.device),
             self.material.reshape(1, 3).expand(n, 3)], dim=-1)

    def _static_node_features(self) -> torch.Tensor:
        """(V, 24) node features that never change; dynamic slots left zero."""
        v, dev = self.num_vertices, self.device
        f = torch.zeros(v, NODE_DIM, device=dev)
        f[:, 9] = self.free.float()
        f[:, 10] = self.pinned.float()
        depth = torch.as_tensor(finest_level_of(self.levels, v), device=dev).clamp_max(3)
        f[:, 11:15] = torch.nn.functional.one_hot(depth, 4).float()
        nl = max(self.num_layers - 1, 1)
        f[:, 15] = self.layer_index.float() / nl
        f[:, 16] = (self.layer_index == self.num_layers - 1).float()
        f[:, 17] = self.dt
        f[:, 18] = torch.log10(self.cloth.vertex_mass.to(dev).float().clamp_min(1e-9))
        f[:, 19] = float(self.cloth.material.friction)
        f[:, 20:23] = self.material
        return f

    def _virtual_edges(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inter-layer nearest-vertex edges (Eq. 5) for positions ``x`` (V, 3) numpy.

        Returns:
            edges (2, Ev) sender/receiver, and a (Ev,) bool mask of the edges whose receiver is the upper
            layer (the repulsion pairs).
        """
        send, recv, up = [], [], []
        for k in range(self.num_layers - 1):
            lo, hi = self.layer_slices[k], self.layer_slices[k + 1]
            q, r = _nearest(x[hi], x[lo], self.virtual_radius)  # upper vertex receives from lower
            send.append(r + lo.start)
            recv.append(q + hi.start)
            up.append(np.ones(q.size, bool))
            q, r = _nearest(x[lo], x[hi], self.virtual_radius)  # lower vertex receives from upper
            send.append(r + hi.start)
            recv.append(q + lo.start)
            up.append(np.zeros(q.size, bool))
        if not send:
            return np.zeros((2, 0), np.int64), np.zeros(0, bool)
        return np.stack([np.concatenate(send), np.concatenate(recv)]), np.concatenate(up)

    def build(
        self,
        x_prev: torch.Tensor,
        x_cur: torch.Tensor,
        body_cur: torch.Tensor,
        body_next: torch.Tensor,
        pinned_next: torch.Tensor | None = None,
        body_tree: PointTree | None = None,
        body_nearest: tuple[np.ndarray, np.ndarray] | None = None,
        body_normals_next: torch.Tensor | None = None,
        body_tree_next: PointTree | None = None,
    ) -> GraphInputs:
        """Features and proximity edges of one step.

        Args:
            x_prev: (V, 3) garment positions at t-1, m.
            x_cur: (V, 3) garment positions at t, m.
            body_cur: (Vb, 3) body vertices at t, m.
            body_next: (Vb, 3) body vertices at t+1, m.
            pinned_next: (V, 3) positions at t+1 whose pinned rows are used (the skinned targets); None =
                pinned vertices keep their velocity.
            body_tree: a prebuilt :func:`smln.geometry.build_tree` over ``body_cur`` (skips building it; e.g. the
                tree the metrics of the previous frame used, see :func:`smln.rollout.rollout`).
            body_nearest: the nearest body vertex (V,) int64 and its distance (V,) m of every ``x_cur`` vertex in
                ``body_cur``, if already known (the metrics of the previous frame found them: ``FrameMetrics
                .body_index`` / ``.body_distance``); skips the body query. Edges keep the pairs closer than the
                body radius, as the query would.
            body_normals_next: (Vb, 3) unit outward vertex normals of ``body_next``; required when the topology
                was built with ``body_normals=True`` (``smln.geometry.vertex_normals(body_next, body_faces)``).
            body_tree_next: a prebuilt KD-tree over ``body_next``, handed on in the inputs (optional).

        Returns:
            :class:`GraphInputs`. Only features and the virtual/body edges are computed here.
        """
        dev = self.device
        x_prev = x_prev.to(dev, torch.float32)
        x_cur = x_cur.to(dev, torch.float32)
        vel = x_cur - x_prev
        x_hat = x_cur + vel
        if pinned_next is None:
            pinned_next = x_hat
        pinned_next = pinned_next.to(dev, torch.float32)
        dt = self.dt

        xn = x_cur.detach().cpu().numpy()
        # body world edges (Eq. 7-8): garment vertex <- nearest body vertex at t
        if body_nearest is not None:
            near_idx, near_dist = body_nearest
            if len(near_idx) != len(xn):
                raise ValueError(f"body_nearest has {len(near_idx)} entries for {len(xn)} garment vertices")
            qb = np.flatnonzero(np.asarray(near_dist) < self.body_radius).astype(np.int64)
            rb = np.asarray(near_idx, dtype=np.int64)[qb]
        else:
            b_np = None if body_tree is not None else body_cur.detach().cpu().numpy()
            qb, rb = _nearest(xn, b_np, self.body_radius, tree=body_tree)
        qb_t = torch.as_tensor(qb, device=dev)
        rb_t = torch.as_tensor(rb, device=dev)
        body_cur = body_cur.to(dev, torch.float32)
        body_next = body_next.to(dev, torch.float32)
        xq = x_cur.index_select(0, qb_t)  # index_select: one index_add in the backward, not an index_put
        d0 = xq - body_cur.index_select(0, rb_t)
        d1 = xq - body_next.index_select(0, rb_t)
        cols = [d0, d0.norm(dim=-1, keepdim=True), d1, d1.norm(dim=-1, keepdim=True),
                torch.full((qb.size, 1), dt, device=dev)]
        if self.body_normals:
            if body_normals_next is None:
                raise ValueError("this topology's body edges carry the body normals: pass body_normals_next "
                                 "(the (Vb, 3) vertex normals of body_next)")
            if body_normals_next.shape != body_next.shape:
                raise ValueError(f"body_normals_next is {tuple(body_normals_next.shape)}, body_next is "
                                 f"{tuple(body_next.shape)}")
            body_normals_next = body_normals_next.to(dev, torch.float32)
            nb = body_normals_next.index_select(0, rb_t)
            cols += [nb, (d1 * nb).sum(dim=-1, keepdim=True)]
        body_feat = torch.cat(cols, dim=-1)

        # virtual inter-layer edges (Eq. 5-6)
        ve, up = self._virtual_edges(xn)
        ve_t = torch.as_tensor(ve, device=dev)
        s, r = ve_t[0], ve_t[1]
        dv = x_cur.index_select(0, s) - x_cur.index_select(0, r)
        dh = x_hat.index_select(0, s) - x_hat.index_select(0, r)
        virt_feat = torch.cat(
            [dv, dv.norm(dim=-1, keepdim=True), dh, dh.norm(dim=-1, keepdim=True),
             torch.full((ve.shape[1], 1), dt, device=dev)], dim=-1)
        up_t = torch.as_tensor(up, device=dev)
        rep_pairs = torch.stack([r[up_t], s[up_t]])  # (outer i, inner j)

        # mesh edges (fine and anchor levels): dynamic columns + the precomputed static ones
        def edge_feat(g: torch.Tensor, static: torch.Tensor) -> torch.Tensor:
            xs = x_cur.index_select(0, g[0]) - x_cur.index_select(0, g[1])
            return torch.cat([xs, xs.norm(dim=-1, keepdim=True), static], dim=-1)

        me = self.mesh_edges
        mesh_feat = edge_feat(me, self.mesh_static)
        coarse_feat = [edge_feat(g, st) for g, st in zip(self.level_global_edges, self.level_static, strict=True)]

        # nodes
        nf = self.static_node.clone()
        nf[:, 0:3] = vel
        nf[:, 3:6] = vertex_normals(x_cur, self.faces)
        pin = self.pinned.unsqueeze(-1)
        nf[:, 6:9] = torch.where(pin, pinned_next - x_cur, torch.zeros_like(x_cur))
        if qb.size:
            nf[qb_t, 23] = 1.0
        return GraphInputs(
            node_features=nf,
            mesh_edges=me,
            mesh_features=mesh_feat,
            coarse_features=coarse_feat,
            virtual_edges=ve_t,
            virtual_features=virt_feat,
            body_receivers=qb_t,
            body_features=body_feat,
            repulsion_pairs=rep_pairs,
            x_cur=x_cur,
            velocity=vel,
            pinned_next=pinned_next,
            body_cur=body_cur,
            body_next=body_next,
            body_normals_next=body_normals_next if self.body_normals else None,
            body_tree_next=body_tree_next,
        )
