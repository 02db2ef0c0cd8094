"""Building garments of the generated types on a body shape, with an on-disk cache.

A garment is keyed by (type, shape, target edge length, body gap) and stored as npz under
``$SMLN_CACHE_DIR/garments`` (default ``~/.cache/smln/garments``). Building one takes well under a few seconds;
loading a cached one takes milliseconds.
"""

from __future__ import annotations

import hashlib
import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from smln.body import load_body
from smln.cloth import Material
from smln.garments.garment import Garment, GarmentError, vertex_mass
from smln.garments.generators import SPECS, generate
from smln.garments.meshops import boundary_loops
from smln.garments.regions import landmarks
from smln.garments.skin_transfer import transfer_weights

GARMENT_TYPES: tuple[str, ...] = tuple(SPECS)
"""The generated garment types."""

DEFAULT_EDGE_LENGTH = 0.02
"""Default target edge length, m."""
TRAINING_EDGE_LENGTH = 0.035
"""Coarser target edge length for training, m."""


@lru_cache(maxsize=1)
def cache_version() -> str:
    """Short hash of the garment-building source files: editing them invalidates the cache."""
    here = Path(__file__).resolve().parent
    text = b"".join((here / n).read_bytes() for n in ("generators.py", "meshops.py", "regions.py",
                                                       "skin_transfer.py", "library.py", "garment.py"))
    return hashlib.sha1(text).hexdigest()[:10]


def cache_dir() -> Path:
    """Directory of cached garments (``$SMLN_CACHE_DIR/garments`` or ``~/.cache/smln/garments``)."""
    root = os.environ.get("SMLN_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "smln") / "garments"


def waist_loop(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Vertex indices of the highest boundary loop (the waistband of a lower-body garment)."""
    loops = boundary_loops(faces)
    if not loops:
        return np.zeros(0, dtype=np.int64)
    return max(loops, key=lambda lp: float(vertices[lp, 2].mean()))


def finish_garment(
    name: str, garment_type: str, vertices: np.ndarray, faces: np.ndarray, body, *, pin_waist: bool,
    loose: np.ndarray | None, material: Material | None = None, edge_length: float = 0.0,
) -> Garment:
    """Attach mass (Eq. 3), pins and transferred skinning weights to a rest mesh."""
    material = material or Material()
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    pinned = np.zeros(len(v), dtype=bool)
    if pin_waist:
        pinned[waist_loop(v, f)] = True
    idx, w = transfer_weights(
        v, f, body.rest_vertices.numpy().astype(np.float64), body.skin_indices.numpy(),
        body.skin_weights.numpy(), body.num_bones, loose=loose, k=body.skin_indices.shape[1],
    )
    return Garment(name, garment_type, v.astype(np.float32), f, vertex_mass(v, f, material.density), pinned, idx, w,
                   material, body.shape, edge_length)


def loose_mask(garment_type: str, vertices: np.ndarray, body) -> np.ndarray | None:
    """Vertices of the loose part whose skinning weights are diffused (None when the type has none)."""
    if not SPECS[garment_type].loose:
        return None
    lm = landmarks(body)
    return vertices[:, 2] < lm.hips_z - 0.02


def build_garment(
    garment_type: str, shape: str = "female_average", edge_length: float = DEFAULT_EDGE_LENGTH,
    offset: float | None = None, use_cache: bool = True,
) -> Garment:
    """Generate (or load from the cache) a garment of ``garment_type`` fitted to body ``shape``.

    Args:
        garment_type: one of :data:`GARMENT_TYPES`.
        shape: body shape preset.
        edge_length: target edge length, m (0.02 default, 0.035 for training).
        offset: gap to the body, m (default: the type's own, see :data:`smln.garments.generators.SPECS`).
        use_cache: read/write the npz cache.

    Raises:
        GarmentError: unknown type or an edge length outside [5 mm, 10 cm].
    """
    if garment_type not in SPECS:
        raise GarmentError(f"unknown garment type {garment_type!r}; choose one of: {', '.join(SPECS)}")
    if not 0.005 <= edge_length <= 0.1:
        raise GarmentError(f"edge length {edge_length} m is outside [0.005, 0.1] m")
    spec = SPECS[garment_type]
    offset = spec.offset if offset is None else float(offset)
    key = f"{cache_version()}_{garment_type}_{shape}_h{round(edge_length * 1e4):d}_o{round(offset * 1e4):d}.npz"
    path = cache_dir() / key
    if use_cache and path.exists():
        try:
            return Garment.load(path)
        except (OSError, ValueError, KeyError):
            path.unlink(missing_ok=True)
    body = load_body(shape)
    v, f = generate(body, garment_type, edge_length, offset)
    g = finish_garment(garment_type, garment_type, v, f, body, pin_waist=spec.pinned_waist,
                       loose=loose_mask(garment_type, v, body), edge_length=edge_length)
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
        g.save(tmp)
        os.replace(tmp, path)
    return g
