"""Garment shapes generated from the body, so they fit every shape preset.

Two constructions:

* **offset garments** (t-shirt, long-sleeve, tank top, open jacket, trousers, shorts, leggings): the closed body
  surface offset along its vertex normals, cut by a few scalar fields (hem, neckline, sleeves, armholes, legs),
  remeshed to near-uniform triangles (:mod:`smln.garments.meshops`), Taubin-smoothed and pushed out of the body;
* **loft garments** (skirt, the skirt of the dress): rings from the waist down whose radius at each angle is the
  body's largest radial extent from the waist down to that height (so the skirt hangs over both legs as one
  cone and never follows one leg), plus a gap and a flare; consecutive rings are zipped into triangles.

Every generator returns ``(vertices (V, 3) float64, faces (F, 3) int64)`` in meters, T-pose, outward faces,
one connected component.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from smln.body import Body
from smln.garments import meshops as mo
from smln.garments.regions import Landmarks, landmarks

Field = Callable[[np.ndarray], np.ndarray]
"""Scalar field on (N, 3) points, meters: <= 0 keeps the point."""


@dataclass(frozen=True)
class GarmentSpec:
    """One garment type.

    Attributes:
        name: type name. offset: default gap to the body, m. loose: vertices below this landmark-relative height
            get diffused skinning weights (None: none). pinned_waist: pin the top boundary loop.
        boundary_loops: expected number of boundary loops. kind: "offset" or "loft" or "dress".
    """

    name: str
    offset: float
    kind: str
    boundary_loops: int
    pinned_waist: bool = False
    loose: bool = False


SPECS: dict[str, GarmentSpec] = {
    s.name: s
    for s in [
        GarmentSpec("tshirt", 0.010, "offset", 4),
        GarmentSpec("longsleeve", 0.010, "offset", 4),
        GarmentSpec("tanktop", 0.009, "offset", 4),
        GarmentSpec("jacket", 0.028, "offset", 3, loose=True),
        GarmentSpec("trousers", 0.014, "offset", 3, pinned_waist=True),
        GarmentSpec("shorts", 0.012, "offset", 3, pinned_waist=True),
        GarmentSpec("leggings", 0.006, "offset", 3, pinned_waist=True),
        GarmentSpec("skirt", 0.014, "loft", 2, pinned_waist=True, loose=True),
        GarmentSpec("dress", 0.010, "dress", 4, loose=True),
    ]
}
"""Garment type name -> :class:`GarmentSpec`."""


def _keep_all(*fields: np.ndarray) -> np.ndarray:
    """Intersection of kept regions (max of fields)."""
    return np.maximum.reduce(fields)


def _remove_both(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Keep field that removes the points where both ``a > 0`` and ``b > 0``."""
    return np.minimum(a, b)


def _neckline(
    p: np.ndarray, lm: Landmarks, width: float = 0.085, depth: float = 0.07, drop: float = 0.06
) -> np.ndarray:
    """Keep field with an elliptic neck hole (half-width ``width``, front scoop ``drop`` below the neck base)."""
    dx = p[:, 0] / width
    dy = (p[:, 1] - lm.neck_y) / depth
    inside = width * (1.0 - np.sqrt(dx**2 + dy**2))
    # lower in front (-Y): the cut height falls linearly towards the front
    z0 = lm.neck_z - 0.03 - drop * np.clip(-(p[:, 1] - lm.neck_y) / depth, 0.0, 1.0)
    return _keep_all(_remove_both(inside, p[:, 2] - z0), p[:, 2] - (lm.neck_z + 0.02))


def _torso_fields(lm: Landmarks, kind: str, h: float) -> list[Field]:
    """Keep fields of the upper-body garments."""
    upper = lm.elbow_x - lm.shoulder_x
    sleeve = {
        "tshirt": lm.shoulder_x + 0.35 * upper,
        "longsleeve": lm.wrist_x - 0.02,
        "jacket": lm.wrist_x - 0.03,
        "tanktop": None,
        "dress": None,
    }[kind]
    hem = {
        "tshirt": lm.hips_z - 0.06,
        "longsleeve": lm.hips_z - 0.05,
        "tanktop": lm.hips_z - 0.03,
        "jacket": max(lm.hips_z - 0.08, lm.crotch_z + 0.04),
        "dress": lm.waist_z,
    }[kind]
    fields: list[Field] = [lambda p: hem - p[:, 2]]
    if kind in ("tanktop", "dress"):
        fields.append(lambda p: _neckline(p, lm, width=0.10, depth=0.08, drop=0.10))
        arm_x = lm.shoulder_x - 0.035
        fields.append(lambda p: _remove_both(np.abs(p[:, 0]) - arm_x, p[:, 2] - (lm.armpit_z - 0.05)))
    else:
        fields.append(lambda p: _neckline(p, lm))
        fields.append(lambda p: np.abs(p[:, 0]) - sleeve)
    if kind == "jacket":  # open front: a slit down the front, at least 3 cm wide
        half = max(0.015, 0.6 * h)
        fields.append(lambda p: _remove_both(half - np.abs(p[:, 0] - lm.centre_xy[0]), lm.neck_y - p[:, 1]))
    return fields


def _leg_fields(lm: Landmarks, kind: str) -> list[Field]:
    """Keep fields of the lower-body garments (waist, leg ends; arms/hands excluded)."""
    top = lm.waist_z - 0.01 if kind != "shorts" else lm.hips_z + 0.05
    bottom = {
        "trousers": lm.ankle_z + 0.04,
        "leggings": lm.ankle_z + 0.06,
        "shorts": lm.crotch_z - 0.45 * (lm.crotch_z - lm.knee_z),
    }[kind]
    return [lambda p: p[:, 2] - top, lambda p: bottom - p[:, 2], lambda p: np.abs(p[:, 0]) - 0.45]


def _seed(lm: Landmarks, kind: str) -> np.ndarray:
    """A point on the garment (picks its connected component)."""
    if kind in ("trousers", "shorts", "leggings"):
        return np.array([lm.centre_xy[0], lm.centre_xy[1] + 0.15, lm.hips_z])
    return np.array([lm.centre_xy[0], lm.centre_xy[1] + 0.15, 0.5 * (lm.armpit_z + lm.waist_z)])


def body_offset_surface(body: Body, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """The closed body mesh moved ``offset`` (m) along its vertex normals (float64, (Vb, 3), (Fb, 3))."""
    v = body.rest_vertices.numpy().astype(np.float64)
    f = body.faces.numpy().astype(np.int64)
    n = mo.vertex_normals_np(v, f)
    return v + offset * n, f


def _cut_fields(v: np.ndarray, f: np.ndarray, fields: list[Field], margin: float) -> tuple[np.ndarray, np.ndarray]:
    field = _keep_all(*[fn(v) for fn in fields]) - margin
    return mo.cut(v, f, field)


def offset_garment(body: Body, kind: str, h: float, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """An offset garment of type ``kind`` with target edge length ``h`` (m) and body gap ``offset`` (m)."""
    lm = landmarks(body)
    fields = _torso_fields(lm, kind, h) if kind in ("tshirt", "longsleeve", "tanktop", "jacket", "dress") else (
        _leg_fields(lm, kind))
    seed = _seed(lm, kind)
    v, f = body_offset_surface(body, offset)
    # 1. generous region, uniform remesh; 2. exact cut on the uniform mesh; 3. even out the boundary
    v, f = mo.keep_component(*_cut_fields(v, f, fields, 3 * h), seed)
    v, f = mo.remesh(v, f, h, 8)
    v, f = mo.keep_component(*_cut_fields(v, f, fields, 0.0), seed)
    v, f = mo.regularize_boundary(v, f, h)
    v, f = mo.remesh(v, f, h, 5)
    v, f = mo.keep_component(v, f, seed)
    v = mo.laplacian_smooth(v, f, iterations=6, alpha=0.5)
    return v, f


def _radial_extent(body: Body, centre: np.ndarray, z: np.ndarray, n_theta: int, dz: float) -> np.ndarray:
    """(len(z), n_theta) largest radial distance of body vertices from the vertical axis at ``centre`` (2,) per
    height slab (|z_vertex - z| < dz) and angle bin; arms and hands (|x| > 0.3 m) are ignored."""
    v = body.rest_vertices.numpy().astype(np.float64)
    v = v[np.abs(v[:, 0] - centre[0]) < 0.3]
    d = v[:, :2] - centre
    r = np.linalg.norm(d, axis=1)
    th = np.floor((np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi)) / (2 * np.pi) * n_theta).astype(np.int64) % n_theta
    out = np.zeros((len(z), n_theta))
    for k, zk in enumerate(z):  # loops over rings (tens), vectorised within
        sel = np.abs(v[:, 2] - zk) < dz
        np.maximum.at(out[k], th[sel], r[sel])
    # fill empty bins with the circular max of their neighbours
    for _ in range(6):
        nb = np.maximum(np.roll(out, 1, axis=1), np.roll(out, -1, axis=1))
        out = np.where(out > 0, out, nb)
    return out


def _smooth_above(ext: np.ndarray, sigma_theta: float = 4.0, sigma_z: float = 1.5) -> np.ndarray:
    """A smooth (Gaussian along angle, wrapping, and along height) profile lifted per ring to stay >= ``ext``."""
    from scipy.ndimage import gaussian_filter1d

    g = gaussian_filter1d(ext, sigma_theta, axis=1, mode="wrap")
    g = gaussian_filter1d(g, sigma_z, axis=0, mode="nearest")
    g = g + np.max(ext - g, axis=1, keepdims=True)
    return np.maximum.accumulate(g, axis=0)


def loft_skirt(
    body: Body, h: float, offset: float, z_top: float, z_hem: float, flare: float = 0.18,
    top_ring: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A skirt loft from ``z_top`` to ``z_hem`` (m), target edge ``h`` (m), gap ``offset`` (m) at the waist and a
    radius growing by ``flare`` m per m below the hips.

    Args:
        top_ring: optional (N, 3) closed loop (ordered counter-clockwise seen from above) to start from (the
            bottom boundary of a bodice); the loft then begins one row below it.

    Returns:
        vertices (V, 3), faces (F, 3); the first ``len(top_ring)`` vertices are the given ring.
    """
    lm = landmarks(body)
    centre = np.asarray(lm.centre_xy)
    row = h * np.sqrt(3) / 2
    z_start = z_top if top_ring is None else z_top - row
    n_rows = max(int(np.ceil((z_start - z_hem) / row)), 1)
    z = np.linspace(z_start, z_hem, n_rows + 1)
    n_theta = 128
    ext = _radial_extent(body, centre, z, n_theta, dz=max(0.6 * row, 0.01))
    if top_ring is not None:  # never narrower than the bodice ring
        d = top_ring[:, :2] - centre
        rb = np.zeros(n_theta)
        tb = np.floor((np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi)) / (2 * np.pi) * n_theta).astype(np.int64) % n_theta
        np.maximum.at(rb, tb, np.linalg.norm(d, axis=1) - offset)
        ext[0] = np.maximum(ext[0], rb)
    ext = np.maximum.accumulate(ext, axis=0)  # hangs straight down over the widest part above
    ext = _smooth_above(ext)
    below = np.clip(lm.hips_z - z, 0.0, None)[:, None]
    radius = ext + offset + flare * below
    theta_grid = np.arange(n_theta + 1) / n_theta * 2 * np.pi
    verts, rings, params = [], [], []
    start = 0
    if top_ring is not None:
        d = top_ring[:, :2] - centre
        t = (np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi)) / (2 * np.pi)
        roll = int(np.argmin(t))
        ring = np.roll(np.arange(len(top_ring)), -roll)
        verts.append(top_ring)
        rings.append(ring)
        params.append(t[ring])
        start = len(top_ring)
    for k in range(len(z)):  # one ring per row
        rr = np.r_[radius[k], radius[k, 0]]
        # perimeter of this ring -> number of vertices
        ang = np.linspace(0, 2 * np.pi, 721)
        fine = np.interp(ang, theta_grid, rr)
        pts = np.stack([np.cos(ang) * fine, np.sin(ang) * fine], 1)
        perim = np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()
        n = max(int(round(perim / h)), 8)
        t = (np.arange(n) + 0.5 * (k % 2)) / n
        r = np.interp(t * 2 * np.pi, theta_grid, rr)
        a = 2 * np.pi * t
        p = np.stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a), np.full(n, z[k])], 1)
        verts.append(p)
        rings.append(start + np.arange(n))
        params.append(t)
        start += n
    faces = [mo.zipper(rings[i], params[i], rings[i + 1], params[i + 1]) for i in range(len(rings) - 1)]
    return np.concatenate(verts), np.concatenate(faces)


def skirt(body: Body, h: float, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """A knee-length A-line skirt from the waist."""
    lm = landmarks(body)
    v, f = loft_skirt(body, h, offset, lm.waist_z - 0.01, lm.knee_z + 0.06)
    return v, f


def dress(body: Body, h: float, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """A sleeveless dress: a bodice (offset garment down to the waist) zipped to a skirt loft down to the knees."""
    lm = landmarks(body)
    bv, bf = offset_garment(body, "dress", h, offset)
    loops = mo.boundary_loops(bf)
    bottom = min(loops, key=lambda lp: bv[lp, 2].mean())
    ring = bv[bottom]
    d = ring[:, :2] - np.asarray(lm.centre_xy)
    ang = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    if ang[-1] < ang[0]:  # make the loop counter-clockwise seen from above
        bottom = bottom[::-1]
        ring = bv[bottom]
    sv, sf = loft_skirt(body, h, offset + 0.004, float(ring[:, 2].mean()), lm.knee_z + 0.02, flare=0.22,
                        top_ring=ring)
    # skirt vertices: the first len(ring) are the bodice ring itself -> map onto the bodice's indices
    n_ring = len(ring)
    remap = np.r_[bottom, len(bv) + np.arange(len(sv) - n_ring)]
    v = np.concatenate([bv, sv[n_ring:]])
    f = np.concatenate([bf, remap[sf]])
    v, f = mo.remesh(v, f, h, 4)
    v = mo.laplacian_smooth(v, f, iterations=4, alpha=0.5)
    return mo.keep_component(v, f)


def generate(body: Body, garment_type: str, h: float, offset: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Generate garment ``garment_type`` on ``body`` (see :data:`SPECS`), target edge ``h`` m.

    Returns:
        vertices (V, 3) float64, faces (F, 3) int64, outward-facing, pushed outside the body by >= 60 % of the
        offset.
    """
    spec = SPECS[garment_type]
    offset = spec.offset if offset is None else offset
    if spec.kind == "offset":
        v, f = offset_garment(body, garment_type, h, offset)
    elif spec.kind == "loft":
        v, f = skirt(body, h, offset)
    else:
        v, f = dress(body, h, offset)
    bv = body.rest_vertices.numpy().astype(np.float64)
    bn = mo.vertex_normals_np(bv, body.faces.numpy())
    v = mo.push_out(v, bv, bn, 0.6 * offset)
    return v, f
