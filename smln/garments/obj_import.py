"""User garments: load and validate an OBJ (or any mesh trimesh reads), fit it to the body, place it in an outfit.

Every rejection raises :class:`~smln.garments.garment.GarmentError` with a one-line message, before anything is
changed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from smln.body import load_body
from smln.cloth import Material
from smln.garments.garment import Garment, GarmentError
from smln.garments.library import finish_garment
from smln.garments.meshops import boundary_loops, components, signed_gap, vertex_normals_np
from smln.garments.regions import landmarks

MAX_VERTICES = 50_000
"""Largest user garment accepted, vertices."""
MAX_EXTENT = 3.0
"""Largest plausible garment extent, m (larger suggests centimetres or millimetres)."""
MIN_EXTENT = 0.05
"""Smallest plausible garment extent, m."""


def _count_obj_vertices(data: bytes) -> int:
    return data.count(b"\nv ") + int(data.startswith(b"v "))


def load_mesh_arrays(path: str | Path, max_vertices: int = MAX_VERTICES) -> tuple[np.ndarray, np.ndarray]:
    """Read and validate a garment mesh file.

    Returns:
        vertices (V, 3) float64 and triangle faces (F, 3) int64 (quads are split by trimesh).

    Raises:
        GarmentError: missing/empty/unreadable file, no faces, non-finite coordinates, too many vertices,
            non-manifold edges, or more than one connected component.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise GarmentError(f"{path}: no such file")
    data = path.read_bytes()
    if not data.strip():
        raise GarmentError(f"{path}: the file is empty")
    if path.suffix.lower() == ".obj" and _count_obj_vertices(data) > max_vertices:
        raise GarmentError(f"{path}: {_count_obj_vertices(data):,} vertices, more than the limit of {max_vertices:,}; "
                           "decimate the garment first")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on junk input
        raise GarmentError(f"{path}: not a readable mesh ({type(exc).__name__}: {str(exc)[:80]})") from None
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    f = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    if len(v) == 0 or len(f) == 0:
        raise GarmentError(f"{path}: no triangle or quad faces found (is it a mesh file?)")
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise GarmentError(f"{path}: vertices must have 3 coordinates and faces 3 corners "
                           f"(got {v.shape[1:]} and {f.shape[1:]})")
    if len(v) > max_vertices:
        raise GarmentError(f"{path}: {len(v):,} vertices, more than the limit of {max_vertices:,}; decimate it first")
    if not np.isfinite(v).all():
        raise GarmentError(f"{path}: {int((~np.isfinite(v)).any(axis=1).sum())} vertices have NaN/inf coordinates")
    used = np.unique(f)
    remap = -np.ones(len(v), dtype=np.int64)
    remap[used] = np.arange(len(used))
    v, f = v[used], remap[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    if (counts > 2).any():
        raise GarmentError(f"{path}: {int((counts > 2).sum())} non-manifold edges (shared by 3+ faces); "
                           "repair the mesh first")
    n_comp = len(np.unique(components(f, len(v))))
    if n_comp != 1:
        raise GarmentError(f"{path}: {n_comp} separate pieces; a garment must be one connected manifold piece")
    return v, f


def check_scale(v: np.ndarray, path: str | Path = "garment") -> None:
    """Reject garments whose size is implausible in meters, suggesting the likely unit."""
    ext = float(np.ptp(v, axis=0).max())
    if ext > MAX_EXTENT:
        unit, factor = ("millimetres", 0.001) if ext > 300 else ("centimetres", 0.01)
        raise GarmentError(f"{path}: garment is {ext:.3g} units across; it looks like {unit}, "
                           f"pass scale={factor} (SMLN uses meters)")
    if ext < MIN_EXTENT:
        raise GarmentError(f"{path}: garment is only {ext:.3g} m across; pass a scale factor (SMLN uses meters)")


def waist_loops(v: np.ndarray, f: np.ndarray, body) -> list[np.ndarray]:
    """Boundary loops that could be pinned as a waistband: nearly horizontal (height spread < 6 cm), between
    the crotch and 15 cm above the waist, going once around the body's vertical axis, with the garment hanging
    below it (fewer than 5 % of the vertices more than 2 cm above it: a t-shirt's hem is not a waistband)."""
    lm = landmarks(body)
    centre = np.asarray(lm.centre_xy)
    out = []
    for loop in boundary_loops(f):
        p = v[loop]
        if np.ptp(p[:, 2]) > 0.06 or not (lm.crotch_z < p[:, 2].mean() < lm.waist_z + 0.15):
            continue
        if (v[:, 2] > p[:, 2].max() + 0.02).mean() > 0.05:
            continue
        ang = np.arctan2(p[:, 1] - centre[1], p[:, 0] - centre[0])
        winding = np.diff(np.unwrap(np.r_[ang, ang[0]]))
        if abs(winding.sum()) > np.pi:  # encircles the axis
            out.append(loop)
    return out


def garment_from_obj(
    path: str | Path, body=None, *, name: str | None = None, scale: float = 1.0, pin_waist: bool = True,
    material: Material | None = None, max_vertices: int = MAX_VERTICES, align: bool = True,
) -> Garment:
    """Load a user's garment (OBJ/PLY/...) as a :class:`Garment` fitted to ``body``.

    The mesh must be in meters in the body's T-pose frame (Z up, facing -Y) after ``scale``. With ``align`` a
    garment whose horizontal centre is more than 2 cm off the body's axis is moved over it. Skinning weights come
    from the nearest body vertex; a waistband loop around the hips (if any) is pinned when ``pin_waist``.

    Raises:
        GarmentError: see :func:`load_mesh_arrays` and :func:`check_scale`.
    """
    body = body or load_body()
    v, f = load_mesh_arrays(path, max_vertices)
    v = v * float(scale)
    check_scale(v, path)
    if align:
        lm = landmarks(body)
        mid = 0.5 * (v[:, :2].min(axis=0) + v[:, :2].max(axis=0))
        off = np.asarray(lm.centre_xy) - mid
        if np.linalg.norm(off) > 0.02:
            v[:, :2] += off
    g = finish_garment(name or Path(path).stem, "user", v, f, body, pin_waist=False, loose=None,
                       material=material)
    if pin_waist:
        loops = waist_loops(v, f, body)
        if loops:
            g.pinned[max(loops, key=lambda lp: v[lp, 2].mean())] = True
    return g


def place_layer(outfit, garment: Garment, index: int | None = None):
    """A new :class:`~smln.garments.outfit.Outfit` with ``garment`` inserted.

    Without ``index`` the layer goes where its mean distance in front of the body ranks among the layers. The
    new layer and every layer outside it are then pushed out of what lies beneath
    (:func:`smln.garments.outfit.settle_layers`), so nothing penetrates at rest.
    """
    from smln.garments.outfit import Outfit, settle_layers

    body = load_body(outfit.shape)
    bv = body.rest_vertices.numpy().astype(np.float64)
    bn = vertex_normals_np(bv, body.faces.numpy())
    if index is None:
        mean_gap = float(signed_gap(garment.vertices.astype(np.float64), bv, bn).mean())
        gaps = [float(signed_gap(g.vertices.astype(np.float64), bv, bn).mean()) for g in outfit.layers]
        index = int(sum(gp < mean_gap for gp in gaps))
    if not 0 <= index <= len(outfit.layers):
        raise GarmentError(f"layer index {index} outside 0..{len(outfit.layers)}")
    layers = [*outfit.layers[:index], garment, *outfit.layers[index:]]
    return Outfit(f"{outfit.name}+{garment.name}", settle_layers(layers, outfit.shape), outfit.shape,
                  outfit.material)
