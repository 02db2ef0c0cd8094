"""Evaluation metrics of one frame and of a sequence (DESIGN.md "Metrics"; LayersNet/PBNS definitions).

All quantities are computed in numpy on the CPU (no gradient). Percentages are in [0, 100].

Per frame (:func:`frame_metrics`), with x the cloth at this frame and b the body:

- ``h_coll`` (%): over all garment vertices i, nearest body vertex h (Euclidean) with its unit vertex normal
  n_h; vertex i collides if (x_i - b_h) . n_h < 0. Fraction of colliding vertices.
- ``l_coll`` (%, LayersNet): over the vertices of the outermost garment, nearest vertex j of the union of all
  inner garments, with j's vertex normal (of its own layer's mesh); collision if (x_i - x_j) . n_j < 0.
  0 for single-layer outfits.
- ``l_coll_{k}_{k-1}`` (%): the same test for each adjacent pair, layer k's vertices against layer k-1 only
  (LayersNet leaves middle layers untested; this covers them). For two layers it equals ``l_coll``.
- ``bend`` (PBNS): mean over interior edges of 1 - cos(angle between the two adjacent face normals).
- ``collision_loss`` (LayersNet ``collision_error`` with one neighbour): for each garment vertex with
  signed body distance d (as in h_coll), nearest body vertex within ``LAYERSNET_RADIUS`` (1 cm) and
  d >= -1 cm, v = min(d - 1 mm, 0); collision_loss = sum v^2 / #(v != 0) (mean over the vertices that violate
  the 1 mm margin; 0 if none), m^2. LayersNet averages up to 4 ball-query neighbours per vertex before
  squaring; we use the nearest vertex. ``layer_collision_loss``: the same between the outermost layer and
  the union of the inner ones (LayersNet's garment-wise variant).
- ``strain_mean`` / ``strain_max``: mean and max over unique edges of |l / l_rest - 1| (0.01 = 1 %).
- ``nan``: 1.0 if any coordinate is not finite, else 0.0. ``exploded``: 1.0 if ``nan`` or strain_max > 1
  (an edge doubled) or a vertex is more than 1 m from its nearest body vertex.

Between two frames (:func:`layer_slip`, in :func:`smln.evaluate.summarise`): ``layer_slip`` (m per frame), the
mean tangential slip of outer-layer vertices over the layer beneath where they touch it (within 5 mm): a jacket
carried by the shoulders of a t-shirt slips ~0; one gliding off them slips steadily.

Per-vertex masks for the viewer: ``body_penetration`` (V,) (the h_coll test) and ``layer_penetration`` (V,)
(vertex of layer k >= 1 behind layer k-1, the per-pair test; False on layer 0).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch

from smln.geometry import PointTree, build_tree
from smln.geometry.mesh_np import dot3, face_cross, normal_sums_at, vertex_normals_at
from smln.geometry.surface import closest_surface_points
from smln.losses.rest import ClothRest

LAYERSNET_MARGIN = 1e-3
"""Collision-loss margin, meters (LayersNet ``thresh``)."""

LAYERSNET_RADIUS = 1e-2
"""Collision-loss neighbourhood and depth cut, meters (LayersNet ``radius``)."""

EXPLODED_STRAIN = 1.0
EXPLODED_DISTANCE = 1.0


@dataclass
class FrameMetrics:
    """Metrics of one frame.

    Attributes:
        values: plain floats (see the module docstring for the keys).
        body_penetration: (V,) bool, vertex behind its nearest body vertex.
        layer_penetration: (V,) bool, vertex behind the layer directly beneath it.
        body_index: (V,) int64 nearest body vertex of each cloth vertex (reusable, e.g. for the graph).
        body_distance: (V,) float32 distance to it, meters (inf where the positions are not finite).
    """

    values: dict[str, float]
    body_penetration: np.ndarray
    layer_penetration: np.ndarray
    body_index: np.ndarray
    body_distance: np.ndarray


def _np32(a: torch.Tensor | np.ndarray) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    return np.ascontiguousarray(a, dtype=np.float32)


def _np_index(a: torch.Tensor | np.ndarray) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    return np.asarray(a, dtype=np.int64)


def _layersnet_loss(d: np.ndarray, dist: np.ndarray) -> float:
    v = np.minimum(d - LAYERSNET_MARGIN, 0.0)
    v = np.where((d >= -LAYERSNET_RADIUS) & (dist < LAYERSNET_RADIUS), v, 0.0)
    n = int(np.count_nonzero(v))
    return float(np.dot(v, v) / n) if n else 0.0


def frame_metrics(
    x: torch.Tensor | np.ndarray,
    body: torch.Tensor | np.ndarray,
    rest: ClothRest,
    body_faces: torch.Tensor | np.ndarray | None = None,
    body_normals: torch.Tensor | np.ndarray | None = None,
    body_tree: PointTree | None = None,
) -> FrameMetrics:
    """All metrics of one frame (definitions in the module docstring).

    Vectorised numpy on the CPU; the KD-tree queries use the threads set by :func:`smln.geometry.set_threads`. Without
    ``body_normals`` only the normals of the body vertices that are some cloth vertex's nearest are computed
    (from the faces around them: the same values as :func:`smln.geometry.vertex_normals` there).

    Args:
        x: (V, 3) cloth positions, meters (Cloth vertex order).
        body: (Vb, 3) body vertices at the same frame, meters.
        rest: :class:`~smln.losses.rest.ClothRest` (faces, edges, rest lengths, hinges, layer slices).
        body_faces: (Fb, 3) int64, needed unless ``body_normals`` is given.
        body_normals: (Vb, 3) unit outward body vertex normals at this frame (:func:`smln.geometry.vertex_normals`).
        body_tree: prebuilt :func:`smln.geometry.build_tree` over ``body`` (skips the build, ~1 ms at 12k; e.g.
            shared with the graph build of the next step, see :func:`smln.rollout.rollout`).

    Returns:
        :class:`FrameMetrics`.
    """
    x = _np32(x)
    b = _np32(body)
    nv = x.shape[0]
    nl = rest.num_layers
    no = np.zeros(nv, dtype=bool)
    if not np.isfinite(x).all():
        keys = [
            "h_coll",
            "l_coll",
            "bend",
            "collision_loss",
            "layer_collision_loss",
            "strain_mean",
            "strain_max",
        ]
        keys += [f"l_coll_{k}_{k - 1}" for k in range(1, nl)]
        values = dict.fromkeys(keys, float("nan"))
        values.update(nan=1.0, exploded=1.0)
        return FrameMetrics(values, no, no.copy(), np.zeros(nv, dtype=np.int64), np.full(nv, np.inf, np.float32))

    # body: H-Coll and the LayersNet collision loss. Coordinate-major (3, N) arrays and np.take: row gathers
    # and reductions over an axis of length 3 are several times slower in numpy.
    if body_normals is None and body_faces is None:
        raise ValueError("frame_metrics needs body_faces or body_normals")
    xt = np.ascontiguousarray(x.T)
    bt = np.ascontiguousarray(b.T)
    tree = body_tree if body_tree is not None else build_tree(b)
    bdist, bidx = tree.query(x, k=1)
    if body_normals is None:
        bn = vertex_normals_at(bt, np.ascontiguousarray(_np_index(body_faces).T), bidx)
    else:
        bn = np.take(_np32(body_normals), bidx, axis=0).T
    d_body = dot3(xt - np.take(bt, bidx, axis=1), bn)
    body_pen = d_body < 0.0

    values: dict[str, float] = {
        "h_coll": 100.0 * float(body_pen.mean()),
        "collision_loss": _layersnet_loss(d_body, bdist),
    }

    # cloth face cross products (2 area * normal): face normals for bend, vertex normals for the layers
    topo = rest.numpy_topology
    ft = topo.faces
    fc = face_cross(xt, ft)

    # layers: per adjacent pair, and outermost against the union of the inner layers
    layer_pen = no.copy()
    if nl > 1:
        sl = rest.layer_slices
        trees = [build_tree(x[s]) for s in sl[:-1]]
        # (query layer, inner layer): the adjacent pairs, then the outermost against the farther inner layers
        pairs = [(k, k - 1) for k in range(1, nl)] + [(nl - 1, k) for k in range(nl - 2)]
        found = []  # loops over layers (2-3), not vertices
        for q, r in pairs:
            dist, idx = trees[r].query(x[sl[q]], k=1)
            found.append((dist, idx + sl[r].start))
        a = normal_sums_at(xt, ft, np.concatenate([g for _, g in found]), cross=fc)
        cn = (a / (np.sqrt(dot3(a, a)) + 1e-12)).astype(np.float32)
        start = 0
        best_d = best_signed = np.zeros(0)
        for (q, r), (dist, g) in zip(pairs, found, strict=True):
            d = dot3(xt[:, sl[q]] - np.take(xt, g, axis=1), cn[:, start : start + len(g)])
            start += len(g)
            if r == q - 1:
                layer_pen[sl[q]] = d < 0.0
                values[f"l_coll_{q}_{r}"] = 100.0 * float((d < 0.0).mean())
                if q == nl - 1:
                    best_d, best_signed = dist, d
            else:  # the union's nearest is the closest of the per-layer nearest
                closer = dist < best_d
                best_d = np.where(closer, dist, best_d)
                best_signed = np.where(closer, d, best_signed)
        values["l_coll"] = 100.0 * float((best_signed < 0.0).mean())
        values["layer_collision_loss"] = _layersnet_loss(best_signed, best_d)
    else:
        values["l_coll"] = 0.0
        values["layer_collision_loss"] = 0.0

    # bend (PBNS): 1 - cos between adjacent face normals
    hf = topo.hinge_faces
    if hf.shape[1]:
        fn = fc / (np.sqrt(dot3(fc, fc)) + 1e-12)
        values["bend"] = float(1.0 - dot3(np.take(fn, hf[0], axis=1), np.take(fn, hf[1], axis=1)).mean())
    else:
        values["bend"] = 0.0

    # edge strain
    et = topo.edges
    de = np.take(xt, et[1], axis=1) - np.take(xt, et[0], axis=1)
    strain = np.abs(np.sqrt(dot3(de, de)) / topo.rest_length - 1.0)
    values["strain_mean"] = float(strain.mean())
    values["strain_max"] = float(strain.max())

    exploded = values["strain_max"] > EXPLODED_STRAIN or float(bdist.max()) > EXPLODED_DISTANCE
    values["nan"] = 0.0
    values["exploded"] = float(exploded)
    return FrameMetrics(values, body_pen, layer_pen, bidx, bdist)


MAX_KEYS = ("h_coll", "l_coll", "strain_max", "collision_loss", "layer_collision_loss", "nan", "exploded")
"""Keys for which :func:`sequence_metrics` also reports the maximum over frames (``<key>_max``)."""


def sequence_metrics(frames: Iterable[FrameMetrics | dict[str, float]]) -> dict[str, float]:
    """Aggregate per-frame metrics over a sequence.

    Every key is averaged over the frames where it is finite (``<key>``); keys in :data:`MAX_KEYS` also get
    ``<key>_max`` over frames (for ``strain_max`` that is ``strain_max_max``). ``nan`` and ``exploded`` are
    the fraction of frames flagged; ``first_exploded_frame`` is the index of the first flagged frame (-1 if
    none); ``num_frames`` the count.

    Args:
        frames: :class:`FrameMetrics` or their ``values`` dicts, in frame order.

    Returns:
        dict of plain floats.
    """
    rows = [f.values if isinstance(f, FrameMetrics) else f for f in frames]
    out: dict[str, float] = {"num_frames": float(len(rows))}
    if not rows:
        return out
    keys = sorted({k for r in rows for k in r})
    for k in keys:
        col = np.array([r.get(k, np.nan) for r in rows], dtype=np.float64)
        fin = col[np.isfinite(col)]
        out[k] = float(fin.mean()) if len(fin) else float("nan")
        if k in MAX_KEYS:
            out[f"{k}_max"] = float(fin.max()) if len(fin) else float("nan")
    flags = [r.get("exploded", 0.0) > 0 or r.get("nan", 0.0) > 0 for r in rows]
    out["first_exploded_frame"] = float(flags.index(True)) if any(flags) else -1.0
    return out


# ----------------------------------------------------------------------------------------- surface L-Coll


def behind_surface(points: np.ndarray, v: np.ndarray, f: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Points behind a triangle surface: closest point c on the triangles (libigl's AABB query through
    gpytoolbox), normal n(c) interpolated from the area-weighted vertex normals (barycentric), behind if
    (p - c) . n(c) < 0. A closest point on the surface's open boundary (an edge of one face, or a vertex of such
    an edge) means the point lies beyond the surface's edge, not behind it: False there.

    Args:
        points: (Q, 3) query points, meters. v: (Nv, 3) surface vertices; f: (F, 3) int64 faces into ``v``.
        tol: barycentric coordinates below this count as zero (closest point on an edge or a vertex).

    Returns:
        (Q,) bool.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    if len(points) == 0 or len(f) == 0:
        return np.zeros(len(points), dtype=bool)
    normals = vertex_normals_at(np.ascontiguousarray(v.T), np.ascontiguousarray(f.T), np.arange(len(v))).T
    sp = closest_surface_points(points, v, f, tol=tol)
    closest = np.einsum("qk,qkd->qd", sp.bary, v[sp.corners])
    n_at = np.einsum("qk,qkd->qd", sp.bary, normals[sp.corners])
    behind = np.einsum("qd,qd->q", points - closest, n_at) < 0.0
    return behind & ~sp.on_boundary & sp.valid


def surface_layer_penetration(
    x: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    layer_index: torch.Tensor | np.ndarray,
) -> np.ndarray:
    """Outermost-layer vertices behind the inner layers' *surface* (a point-to-triangle L-Coll).

    L-Coll (LayersNet) tests each outer vertex against its nearest inner *vertex* and that vertex's normal. On
    coarse meshes a correct contact a few millimetres apart can read as a collision when the nearest inner vertex
    sits beside the contact on a curved or wrinkled patch (a ridge, a fold); a simulator that resolves triangle
    contacts is marked down for it. This test uses :func:`behind_surface` against the union of the inner layers'
    triangles; a closest point on an inner layer's hem means the outer vertex lies beyond that garment.

    Args:
        x: (V, 3) positions of all layers, meters.
        faces: (F, 3) int64 faces of all layers (each face within one layer).
        layer_index: (V,) int64 layer of each vertex, 0 = innermost.

    Returns:
        (V,) bool mask, True for colliding vertices of the outermost layer (False elsewhere, and everywhere for
        single-layer outfits).
    """
    x = _np32(x)
    faces = _np_index(faces)
    li = _np_index(layer_index)
    out = np.zeros(len(x), dtype=bool)
    top = int(li.max()) if len(li) else 0
    if top == 0:
        return out
    outer = np.flatnonzero(li == top)
    out[outer] = behind_surface(x[outer], x, faces[li[faces[:, 0]] < top])
    return out


def surface_h_coll(x: torch.Tensor | np.ndarray, body: torch.Tensor | np.ndarray,
                   body_faces: torch.Tensor | np.ndarray) -> float:
    """% of garment vertices behind the body's surface (:func:`behind_surface` against the closed body mesh): the
    point-to-triangle counterpart of ``h_coll`` (which uses the nearest body vertex and its normal)."""
    x = _np32(x)
    return 100.0 * float(behind_surface(x, _np32(body), _np_index(body_faces)).mean()) if len(x) else 0.0


def surface_l_coll(x: torch.Tensor | np.ndarray, faces: torch.Tensor | np.ndarray,
                   layer_index: torch.Tensor | np.ndarray) -> float:
    """% of the outermost layer's vertices behind the inner layers' surface (:func:`surface_layer_penetration`);
    0 for single-layer outfits. Same denominator as ``l_coll`` (the outermost layer's vertex count)."""
    li = _np_index(layer_index)
    top = int(li.max()) if len(li) else 0
    if top == 0:
        return 0.0
    mask = surface_layer_penetration(x, faces, li)
    return 100.0 * float(mask[li == top].mean())


# ----------------------------------------------------------------------------------------- layer slip


def layer_slip(x_prev: torch.Tensor | np.ndarray, x_cur: torch.Tensor | np.ndarray, rest: ClothRest,
               radius: float | None = None) -> float:
    """Mean tangential slip between touching layers from one frame to the next, meters (NaN if none touch).

    Pairs are each outer-layer vertex with its nearest vertex of the layer beneath at ``x_prev``
    (:func:`smln.losses.repulsion.layer_pairs`, within 4 cm); a pair touches when the outer vertex is less than
    ``radius`` (default :data:`smln.losses.friction.LAYER_FRICTION_RADIUS`, 5 mm) in front of its partner along
    the partner's normal at ``x_cur``. Its slip is the relative displacement s = Δx_outer - Δx_inner minus its part
    along that normal; the result is the mean |s| over touching pairs with a free outer vertex.

    Args:
        x_prev, x_cur: (V, 3) cloth positions at two consecutive frames, meters.
        rest: layer slices, faces, free mask.
        radius: contact distance, meters.

    Returns:
        float, meters per frame.
    """
    from smln.geometry import vertex_normals
    from smln.losses.friction import LAYER_FRICTION_RADIUS, layer_contact_slip
    from smln.losses.repulsion import layer_pairs

    if rest.num_layers < 2:
        return float("nan")
    radius = LAYER_FRICTION_RADIUS if radius is None else radius
    xp = torch.as_tensor(np.asarray(x_prev, dtype=np.float32))
    xc = torch.as_tensor(np.asarray(x_cur, dtype=np.float32))
    if not (torch.isfinite(xp).all() and torch.isfinite(xc).all()):
        return float("nan")
    pairs = layer_pairs(xp, rest)
    if pairs.numel() == 0:
        return float("nan")
    st, touching, _ = layer_contact_slip(xp, xc, vertex_normals(xc, rest.faces), pairs, rest, radius)
    if not touching.any():
        return float("nan")
    return float(st.norm(dim=-1)[touching].mean())

