"""Mesh operations used to build garments: level-set cuts, components, boundary loops, uniform remeshing,
smoothing and pushing vertices out of an underlying surface.

Everything is vectorised numpy on ``(V, 3)`` float64 positions (meters) and ``(F, 3)`` int64 faces; remeshing is
gpytoolbox's Botsch-Kobbelt remesher with the open boundary passed as feature edges, so boundary loops are
resampled to the target length too.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def face_normals_np(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Unnormalised face normals (F, 3): norm = 2 * area."""
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def vertex_normals_np(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3)."""
    c = face_normals_np(v, f)
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], c)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def vertex_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Barycentric vertex areas (V,), m^2: a third of each adjacent triangle's area."""
    a = 0.5 * np.linalg.norm(face_normals_np(v, f), axis=1)
    out = np.zeros(len(v))
    for k in range(3):
        np.add.at(out, f[:, k], a / 3.0)
    return out


def adjacency(f: np.ndarray, n: int) -> sp.csr_matrix:
    """Symmetric (n, n) vertex adjacency matrix of the mesh edges (ones)."""
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    return a


def components(f: np.ndarray, n: int) -> np.ndarray:
    """(n,) connected-component label of each vertex (isolated vertices get their own label)."""
    return connected_components(adjacency(f, n), directed=False)[1]


def compact(v: np.ndarray, f: np.ndarray, keep_faces: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Keep ``keep_faces`` (bool mask, default all) and drop unreferenced vertices."""
    if keep_faces is not None:
        f = f[keep_faces]
    used = np.unique(f)
    remap = -np.ones(len(v), dtype=np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def keep_component(v: np.ndarray, f: np.ndarray, seed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Keep one connected component: the one nearest to ``seed`` (3,), else the largest by vertex count."""
    v, f = compact(v, f)
    lab = components(f, len(v))
    if seed is None:
        target = np.bincount(lab).argmax()
    else:
        target = lab[np.argmin(np.linalg.norm(v - seed, axis=1))]
    return compact(v, f, lab[f[:, 0]] == target)


def boundary_edges(f: np.ndarray) -> np.ndarray:
    """(E, 2) directed boundary edges (edges used by exactly one face), in face winding order."""
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.sort(e, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return e[cnt[inv.ravel()] == 1]


def boundary_loops(f: np.ndarray) -> list[np.ndarray]:
    """Boundary loops as ordered vertex index arrays (one per loop), following the face winding."""
    e = boundary_edges(f)
    if len(e) == 0:
        return []
    nxt = dict(zip(e[:, 0].tolist(), e[:, 1].tolist(), strict=False))
    loops, seen = [], set()
    for start in e[:, 0].tolist():  # loops over boundary vertices only
        if start in seen:
            continue
        loop, cur = [], start
        while cur not in seen:
            seen.add(cur)
            loop.append(cur)
            cur = nxt.get(cur, start)
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def cut(v: np.ndarray, f: np.ndarray, field: np.ndarray, snap: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Keep the part of a mesh where a scalar field is <= 0, splitting the triangles that cross its zero set.

    The zero set is linearly interpolated along edges. Field values within ``snap`` times the mean absolute
    edge difference of zero are set to zero first, so the cut passes through those vertices instead of
    creating slivers.

    Args:
        v: (V, 3) positions; f: (F, 3) faces; field: (V,) scalar field (any unit).

    Returns:
        (V', 3) positions and (F', 3) faces of the kept part (unreferenced vertices dropped).
    """
    field = np.asarray(field, dtype=np.float64).copy()
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    scale = np.mean(np.abs(field[e[:, 0]] - field[e[:, 1]]))
    field[np.abs(field) < snap * scale] = 0.0
    s = np.sign(field).astype(np.int64)  # -1 keep, 0 on the cut, +1 drop
    fs = s[f]
    # new vertices on edges with strictly opposite signs
    a, b = f, np.roll(f, -1, axis=1)  # edges (k, k+1)
    cross = (s[a] * s[b]) < 0
    ea, eb = a[cross], b[cross]
    key = np.sort(np.stack([ea, eb], 1), axis=1)
    ukey, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    fa, fb = field[ukey[:, 0]], field[ukey[:, 1]]
    t = (fa / (fa - fb))[:, None]
    newv = v[ukey[:, 0]] * (1 - t) + v[ukey[:, 1]] * t
    edge_vid = -np.ones(f.shape, dtype=np.int64)
    edge_vid[cross] = len(v) + inv
    # polygon slots: corner k (if kept side or on cut), then the point on edge (k, k+1) (if crossing)
    slots = np.stack([f[:, 0], edge_vid[:, 0], f[:, 1], edge_vid[:, 1], f[:, 2], edge_vid[:, 2]], axis=1)
    valid = np.stack([fs[:, 0] <= 0, cross[:, 0], fs[:, 1] <= 0, cross[:, 1], fs[:, 2] <= 0, cross[:, 2]], axis=1)
    has_keep = (fs < 0).any(axis=1) | (fs == 0).all(axis=1)
    order = np.argsort(~valid, axis=1, kind="stable")
    poly = np.take_along_axis(slots, order, axis=1)
    k = valid.sum(axis=1)
    tri1 = (k >= 3) & has_keep
    tri2 = (k == 4) & has_keep
    faces = np.concatenate([poly[tri1][:, [0, 1, 2]], poly[tri2][:, [0, 2, 3]]])
    return compact(np.concatenate([v, newv]), faces)


def remesh(v: np.ndarray, f: np.ndarray, h: float, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remesh to target edge length ``h`` (m); open boundaries are resampled along themselves."""
    import gpytoolbox

    fe = boundary_edges(f)
    u, g = gpytoolbox.remesh_botsch(
        np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(f, dtype=np.int32), iterations, h, True,
        feature_edges=fe.astype(np.int32) if len(fe) else None,
    )
    return compact(np.asarray(u, dtype=np.float64), np.asarray(g, dtype=np.int64))


def laplacian_smooth(
    v: np.ndarray, f: np.ndarray, iterations: int = 5, alpha: float = 0.5, fixed: np.ndarray | None = None,
    taubin: bool = True,
) -> np.ndarray:
    """Uniform-Laplacian (Taubin lambda/mu) smoothing; ``fixed`` (V,) bool vertices do not move.

    Boundary vertices are smoothed along their boundary neighbours only, so loops keep their shape.
    """
    n = len(v)
    adj = adjacency(f, n)
    be = boundary_edges(f)
    on_b = np.zeros(n, bool)
    on_b[be.ravel()] = True
    badj = sp.coo_matrix((np.ones(2 * len(be)), (np.r_[be[:, 0], be[:, 1]], np.r_[be[:, 1], be[:, 0]])),
                         shape=(n, n)).tocsr()
    adj = sp.diags((~on_b).astype(float)) @ adj + sp.diags(on_b.astype(float)) @ badj
    deg = np.asarray(adj.sum(axis=1)).ravel()
    w = sp.diags(1.0 / np.maximum(deg, 1)) @ adj
    x = v.copy()
    move = np.ones(n, bool) if fixed is None else ~fixed
    for it in range(iterations):
        for lam in ((alpha, -alpha * 1.04) if taubin else (alpha,)):
            d = w @ x - x
            x[move] += lam * d[move]
        del it
    return x


def push_out(
    x: np.ndarray, under_v: np.ndarray, under_n: np.ndarray, clearance: float, iterations: int = 4,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Move points outside an underlying surface by at least ``clearance`` (m).

    For each point the nearest underlying vertex ``h`` (normal ``n_h``) is found; if (x - x_h) . n_h < clearance
    the point moves along ``n_h`` to the clearance. Repeated because the nearest vertex may change.

    Args:
        x: (N, 3) points; under_v: (M, 3) underlying vertices; under_n: (M, 3) their unit normals.

    Returns:
        (N, 3) moved copy of ``x``.
    """
    tree = tree or cKDTree(under_v)
    x = x.copy()
    for _ in range(iterations):
        _, j = tree.query(x)
        d = np.einsum("ij,ij->i", x - under_v[j], under_n[j])
        bad = d < clearance
        if not bad.any():
            break
        x[bad] += (clearance - d[bad])[:, None] * under_n[j[bad]]
    return x


def signed_gap(x: np.ndarray, under_v: np.ndarray, under_n: np.ndarray) -> np.ndarray:
    """(N,) signed distance of points in front of the nearest underlying vertex's normal plane, m."""
    _, j = cKDTree(under_v).query(x)
    return np.einsum("ij,ij->i", x - under_v[j], under_n[j])


def zipper(ring_a: np.ndarray, ta: np.ndarray, ring_b: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """Triangulate the band between two closed vertex rings ordered by an increasing angular parameter.

    Args:
        ring_a, ring_b: (Na,), (Nb,) vertex ids; ta, tb: their parameters in [0, 1), increasing.

    Returns:
        (Na + Nb, 3) faces; with ring_a above ring_b and the parameter increasing counter-clockwise seen from
        above, the faces face outward.
    """
    na, nb = len(ring_a), len(ring_b)
    # events: advancing ring a to its next vertex (param ta[i+1]) or ring b
    ea = np.r_[ta[1:], 1.0 + ta[0]]
    eb = np.r_[tb[1:], 1.0 + tb[0]]
    lab = np.r_[np.zeros(na, bool), np.ones(nb, bool)]
    order = np.argsort(np.r_[ea, eb], kind="stable")
    lab = lab[order]
    i = np.cumsum(~lab) - (~lab)  # a-steps before this event
    j = np.cumsum(lab) - lab
    a0, a1 = ring_a[i % na], ring_a[(i + 1) % na]
    b0, b1 = ring_b[j % nb], ring_b[(j + 1) % nb]
    return np.where(lab[:, None], np.stack([a0, b0, b1], 1), np.stack([a0, b0, a1], 1))


def regularize_boundary(v: np.ndarray, f: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Collapse boundary vertices so each boundary loop is sampled about every ``h`` (m) of arc length.

    Each loop is split into ``round(length / h)`` equal arc-length buckets; the first vertex of each bucket stays
    (moved onto the bucket's start point of the polyline) and the rest of the bucket collapses into it.
    Follow with :func:`remesh` to even out the triangles next to the boundary.
    """
    target = np.arange(len(v))
    newpos = v.copy()
    for loop in boundary_loops(f):  # loops over boundary loops, not vertices
        p = v[loop]
        seg = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)
        cum = np.r_[0.0, np.cumsum(seg)[:-1]]
        total = seg.sum()
        n = max(int(round(total / h)), 3)
        if n >= len(loop):
            continue
        step = total / n
        bucket = np.minimum((cum / step + 1e-9).astype(np.int64), n - 1)
        first = np.r_[True, bucket[1:] != bucket[:-1]]
        head = loop[first][np.cumsum(first) - 1]
        target[loop] = head
        # move each kept vertex to the exact start of its bucket along the polyline
        s = bucket[first] * step
        k = np.searchsorted(cum, s, side="right") - 1
        t = ((s - cum[k]) / np.maximum(seg[k], 1e-12))[:, None]
        newpos[loop[first]] = p[k] * (1 - t) + np.roll(p, -1, axis=0)[k] * t
    g = target[f]
    ok = (g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])
    return compact(newpos, g[ok])
