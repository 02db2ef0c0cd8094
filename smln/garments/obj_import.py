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

FILE_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "inch": 0.0254}
"""Meters per file unit tried when no scale is given (the ones whose garment size is plausible)."""

UP_AXES = {"z": np.eye(3), "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}
"""File frame -> body frame (Z up, facing -Y): ``z`` as it is; ``y`` the Y-up, facing +Z frame of OBJ exporters
(Blender's default), (x, y, z) -> (x, -z, y)."""

MAX_BODY_DISTANCE = 0.15
"""Largest median distance of a garment's vertices from the T-pose body surface, m (shipped garments: 1-7 cm)."""

BELOW_FLOOR = (0.02, 0.05)
"""A reading with more than 5 % of its vertices 2 cm or more below the floor (z = 0, where the body stands) is not
on the body: a Y-up garment read as Z-up lies on the floor, half of it below."""

INSIDE_BODY = (0.01, 0.05)
"""A reading with more than 5 % of its vertices 1 cm or more inside the body (behind the nearest body vertex's
normal plane) is not on it: an inch garment read as cm is shrunk into the torso."""

SWITCH_FACTOR = 0.5
"""Another unit or up axis replaces the file's own (meters, Z up) only when its median distance from the body is
below this fraction of the file's own."""


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


def _centred(v: np.ndarray, centre_xy: np.ndarray) -> np.ndarray:
    """``v`` moved horizontally so that its bounding box is centred on ``centre_xy`` (when more than 2 cm off)."""
    off = centre_xy - 0.5 * (v[:, :2].min(axis=0) + v[:, :2].max(axis=0))
    if np.linalg.norm(off) <= 0.02:
        return v
    out = v.copy()
    out[:, :2] += off
    return out


def fit_to_body(v: np.ndarray, body, path: str | Path = "garment", scale: float | None = None,
                up_axis: str | None = None, align: bool = True) -> tuple[np.ndarray, str]:
    """The garment's vertices in the body frame, meters: the file unit and up axis that put it on the T-pose body.

    Every combination of a unit (``scale``, or those of :data:`FILE_UNITS` whose garment size is plausible) and an up
    axis (``up_axis``, or both of :data:`UP_AXES`) is centred over the body (with ``align``) and scored by the median
    distance of its vertices from the nearest body vertex; readings partly below the floor (:data:`BELOW_FLOOR`) or
    inside the body (:data:`INSIDE_BODY`) are out. The file's own reading (meters or the given scale, Z up) is kept
    unless another scores below :data:`SWITCH_FACTOR` of it.

    Args:
        v: (V, 3) float64 vertices in file units; body: the T-pose body; scale: meters per file unit, None to
            detect it; up_axis: ``"z"``, ``"y"`` or None to detect it.

    Returns:
        (V, 3) float64 vertices, meters, and a note of what was changed ("" when nothing was).

    Raises:
        GarmentError: an implausible size for a given scale (:func:`check_scale`), no plausible unit, an unknown
            up axis, or no reading within :data:`MAX_BODY_DISTANCE` of the body.
    """
    from scipy.spatial import cKDTree

    if up_axis is not None and up_axis not in UP_AXES:
        raise GarmentError(f"{path}: up axis {up_axis!r} is not one of {', '.join(UP_AXES)}")
    if scale is not None:
        check_scale(v * float(scale), path)
        units = {"the given scale": float(scale)}
    else:
        ext = float(np.ptp(v, axis=0).max())
        units = {k: u for k, u in FILE_UNITS.items() if MIN_EXTENT <= ext * u <= MAX_EXTENT}
        if not units:
            check_scale(v, path)  # raises with the hint for meters
    axes = [up_axis] if up_axis is not None else list(UP_AXES)
    body_v = body.rest_vertices.numpy().astype(np.float64)
    body_n = vertex_normals_np(body_v, body.faces.numpy())
    tree = cKDTree(body_v)
    centre = np.asarray(landmarks(body).centre_xy)
    readings = {}
    for unit_name, unit in units.items():
        for axis in axes:
            x = (v * unit) @ UP_AXES[axis].T
            x = _centred(x, centre) if align else x
            distance, nearest = tree.query(x)
            gap = np.einsum("ij,ij->i", x - body_v[nearest], body_n[nearest])  # signed, m
            off = (x[:, 2] < -BELOW_FLOOR[0]).mean() > BELOW_FLOOR[1] or (gap < -INSIDE_BODY[0]).mean() > INSIDE_BODY[1]
            readings[(unit_name, axis)] = (np.inf if off else float(np.median(distance)), x)
    best = min(readings, key=lambda k: readings[k][0])
    own = next(iter(readings))  # meters (or the given scale) and Z up come first
    if own[0] in ("m", "the given scale") and readings[best][0] >= SWITCH_FACTOR * readings[own][0]:
        best = own
    distance, x = readings[best]
    if not np.isfinite(distance):
        raise GarmentError(f"{path}: the garment lies below the floor or inside the body in every unit and up axis "
                           "tried; model it on the body in its T-pose, feet on z = 0 (`smln outfit NAME --out FILE` "
                           "exports it)")
    if distance > MAX_BODY_DISTANCE:
        raise GarmentError(f"{path}: the garment does not sit on the T-pose body (its vertices are a median "
                           f"{100 * distance:.0f} cm from it in every unit and up axis tried); model it on the body "
                           "in its T-pose (`smln outfit NAME --out FILE` exports it)")
    note = [] if best[0] in ("m", "the given scale") else [f"read in {best[0]}"]
    note += [] if best[1] == "z" else ["turned from Y up to Z up"]
    return x, ", ".join(note)


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
    path: str | Path, body=None, *, name: str | None = None, scale: float | None = None, up_axis: str | None = None,
    pin_waist: bool = True, material: Material | None = None, max_vertices: int = MAX_VERTICES, align: bool = True,
) -> Garment:
    """Load a user's garment (OBJ/PLY/...) as a :class:`Garment` fitted to ``body``.

    The mesh must be modeled on the body's T-pose. Its unit (``scale`` meters per file unit) and up axis (``"z"``:
    the body's frame, Z up facing -Y; ``"y"``: Y up facing +Z, as OBJ exporters write) are read from how well it
    fits the body when not given (:func:`fit_to_body`). With ``align`` a garment whose horizontal centre is more than
    2 cm off the body's axis is moved over it. Skinning weights come from the nearest body vertex; a waistband loop
    around the hips (if any) is pinned when ``pin_waist``. What was detected is in the garment's ``note``.

    Raises:
        GarmentError: see :func:`load_mesh_arrays`, :func:`check_scale` and :func:`fit_to_body`.
    """
    body = body or load_body()
    v, f = load_mesh_arrays(path, max_vertices)
    v, note = fit_to_body(v, body, path, scale=scale, up_axis=up_axis, align=align)
    g = finish_garment(name or Path(path).stem, "user", v, f, body, pin_waist=False, loose=None,
                       material=material)
    if pin_waist:
        loops = waist_loops(v, f, body)
        if loops:
            g.pinned[max(loops, key=lambda lp: v[lp, 2].mean())] = True
    g.note = note
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
