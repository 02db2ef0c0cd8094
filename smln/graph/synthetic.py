"""Synthetic scenes for tests and benchmarks: concentric open tubes (garment layers) around a capsule body
driven by a one-bone rigid motion. Not a garment generator (that is ``smln.garments``)."""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh

from smln.cloth import Cloth, Material


def tube(radius: float, height: float, n_around: int, n_rings: int, z0: float = 0.0) -> tuple[
    np.ndarray, np.ndarray
]:
    """Open cylinder along +Z, ring-major vertex order, outward-facing triangles.

    Returns:
        vertices (n_rings * n_around, 3) float32 m, faces (2 * n_around * (n_rings - 1), 3) int64.
        Unique edges: n_around * n_rings + 2 * n_around * (n_rings - 1).
    """
    ang = np.arange(n_around) * (2 * math.pi / n_around)
    z = z0 + np.linspace(0.0, height, n_rings)
    v = np.stack(
        [np.tile(radius * np.cos(ang), n_rings), np.tile(radius * np.sin(ang), n_rings), np.repeat(z, n_around)],
        axis=1,
    ).astype(np.float32)
    r, a = np.meshgrid(np.arange(n_rings - 1), np.arange(n_around), indexing="ij")
    i00 = r * n_around + a
    i01 = r * n_around + (a + 1) % n_around
    i10 = i00 + n_around
    i11 = i01 + n_around
    f = np.concatenate([np.stack([i00, i01, i11], -1).reshape(-1, 3), np.stack([i00, i11, i10], -1).reshape(-1, 3)])
    return v, f.astype(np.int64)


def _vertex_mass(v: np.ndarray, f: np.ndarray, density: float) -> np.ndarray:
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    m = np.zeros(len(v))
    np.add.at(m, f.reshape(-1), np.repeat(area * density / 3.0, 3))
    return m.astype(np.float32)


def tube_outfit(
    radii: tuple[float, ...] = (0.12, 0.126),
    height: float = 0.4,
    n_around: int = 24,
    n_rings: int = 10,
    z0: float = 0.5,
    pin_top: bool = True,
) -> Cloth:
    """Concentric tube layers (inner -> outer) as a :class:`Cloth`; top ring pinned, all skinned to bone 0."""
    vs, fs, li = [], [], []
    off = 0
    for k, rad in enumerate(radii):
        v, f = tube(rad, height, n_around, n_rings, z0)
        vs.append(v)
        fs.append(f + off)
        li.append(np.full(len(v), k))
        off += len(v)
    v = np.concatenate(vs)
    f = np.concatenate(fs)
    mat = Material()
    mass = _vertex_mass(v, f, mat.density)
    pinned = np.zeros(len(v), bool)
    if pin_top:
        pinned = v[:, 2] >= z0 + height - 1e-6
    n = len(v)
    return Cloth(
        rest_vertices=torch.as_tensor(v),
        faces=torch.as_tensor(f),
        layer_index=torch.as_tensor(np.concatenate(li)),
        vertex_mass=torch.as_tensor(mass),
        pinned=torch.as_tensor(pinned),
        skin_indices=torch.zeros(n, 1, dtype=torch.int64),
        skin_weights=torch.ones(n, 1),
        material=mat,
        layer_names=[f"tube{k}" for k in range(len(radii))],
    )


def capsule_body(radius: float = 0.1, height: float = 1.2, max_edge: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """A closed capsule standing on z = 0 with near-uniform vertex spacing (<= ``max_edge``, m).

    Returns: vertices (Vb, 3) float32, faces (Fb, 3) int64.
    """
    cap = trimesh.creation.capsule(height=height - 2 * radius, radius=radius, count=[24, 24])
    v, f = trimesh.remesh.subdivide_to_size(cap.vertices, cap.faces, max_edge=max_edge)
    v = v + np.array([0.0, 0.0, height / 2])
    return v.astype(np.float32), np.asarray(f, dtype=np.int64)


def sway_motion(
    num_frames: int, amplitude: float = 0.05, period: float = 1.0, angle: float = 0.3, fps: float = 30.0
) -> torch.Tensor:
    """One-bone rigid motion: sideways sway of ``amplitude`` (m) and a rotation about Z of ``angle`` (rad).

    Returns: (T, 1, 4, 4) float32 rest -> posed transforms.
    """
    t = torch.arange(num_frames, dtype=torch.float32) / fps
    ph = 2 * math.pi * t / period
    ang = angle * torch.sin(ph)
    m = torch.zeros(num_frames, 1, 4, 4)
    m[:, 0, 0, 0] = torch.cos(ang)
    m[:, 0, 0, 1] = -torch.sin(ang)
    m[:, 0, 1, 0] = torch.sin(ang)
    m[:, 0, 1, 1] = torch.cos(ang)
    m[:, 0, 2, 2] = 1.0
    m[:, 0, 3, 3] = 1.0
    m[:, 0, 0, 3] = amplitude * torch.sin(ph)
    return m


def rigid_lbs(points: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Skin points (N, 3) rigidly with bone 0 of (T, B, 4, 4) transforms -> (T, N, 3)."""
    r = transforms[:, 0, :3, :3]
    tr = transforms[:, 0, :3, 3]
    return torch.einsum("tij,nj->tni", r, points) + tr[:, None, :]


def cylinder_body(radius: float = 0.1, height: float = 1.2, n_around: int = 120, n_rings: int = 100) -> tuple[
    np.ndarray, np.ndarray
]:
    """A closed cylinder standing on z = 0 (side ``tube`` plus two cap centres): a body of exactly
    ``n_around * n_rings + 2`` vertices for benchmarks.

    Returns: vertices (Vb, 3) float32, faces (Fb, 3) int64 (outward).
    """
    v, f = tube(radius, height, n_around, n_rings)
    n = len(v)
    centres = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, height]], np.float32)
    a = np.arange(n_around)
    b = (a + 1) % n_around
    top = (n_rings - 1) * n_around
    bottom = np.stack([np.full(n_around, n), b, a], 1)
    cap = np.stack([np.full(n_around, n + 1), top + a, top + b], 1)
    return np.concatenate([v, centres]), np.concatenate([f, bottom, cap]).astype(np.int64)
