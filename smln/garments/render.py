"""Pictures of outfits on the body: orthographic front and side views, painter's algorithm, Lambert shading.

All faces (body and layers) are sorted together by depth and drawn as one matplotlib ``PolyCollection``, so layers
occlude each other correctly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from smln.body import load_body

LAYER_COLOURS = [(0.20, 0.45, 0.85), (0.90, 0.45, 0.15), (0.25, 0.70, 0.35), (0.75, 0.30, 0.65)]
BODY_COLOUR = (0.80, 0.78, 0.75)
VIEWS = {"front": (np.array([1.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])),  # (screen x axis, towards viewer)
         "side": (np.array([0.0, -1.0, 0.0]), np.array([-1.0, 0.0, 0.0])),
         "back": (np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))}


def draw_meshes(ax, meshes: list[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]], view: str) -> None:
    """Draw (vertices (V, 3), faces (F, 3), rgb) meshes on a 2-D matplotlib axis from ``view``."""
    from matplotlib.collections import PolyCollection

    sx, toward = VIEWS[view]
    light = toward + np.array([0.0, 0.0, 0.6]) + 0.4 * sx
    light /= np.linalg.norm(light)
    polys, cols, depth = [], [], []
    for v, f, rgb in meshes:
        tri = v[f]  # (F, 3, 3)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        shade = 0.35 + 0.65 * np.abs(n @ light)  # two-sided (insides of open garments show)
        back = (n @ toward) < 0
        shade = np.where(back, shade * 0.6, shade)
        polys.append(np.stack([tri @ sx, tri[..., 2]], axis=-1))
        cols.append(np.clip(np.asarray(rgb)[None] * shade[:, None], 0, 1))
        depth.append((tri @ toward).mean(axis=1))
    p, c, d = np.concatenate(polys), np.concatenate(cols), np.concatenate(depth)
    order = np.argsort(d)
    ax.add_collection(PolyCollection(p[order], facecolors=c[order], edgecolors="none", antialiased=False))
    allp = p.reshape(-1, 2)
    ax.set_xlim(allp[:, 0].min() - 0.05, allp[:, 0].max() + 0.05)
    ax.set_ylim(allp[:, 1].min() - 0.05, allp[:, 1].max() + 0.05)
    ax.set_aspect("equal")
    ax.axis("off")


def outfit_meshes(outfit) -> list[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]]:
    """Body plus layers as (vertices, faces, colour) tuples."""
    body = load_body(outfit.shape)
    out = [(body.rest_vertices.numpy(), body.faces.numpy(), BODY_COLOUR)]
    for i, g in enumerate(outfit.layers):
        out.append((g.vertices, g.faces, LAYER_COLOURS[i % len(LAYER_COLOURS)]))
    return out


def render_outfit(outfit, path: str | Path, views: tuple[str, ...] = ("front", "side", "back"), dpi: int = 110) -> Path:
    """Write a PNG of ``outfit`` on its body from ``views``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(views), figsize=(3.2 * len(views), 5.2))
    meshes = outfit_meshes(outfit)
    for ax, view in zip(np.atleast_1d(axes), views, strict=True):
        draw_meshes(ax, meshes, view)
    layers = " + ".join(f"{g.garment_type} ({g.num_vertices} v)" for g in outfit.layers)
    fig.suptitle(f"{outfit.name} on {outfit.shape}: {layers}", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def render_overview(outfits: list, path: str | Path, view: str = "front", dpi: int = 100) -> Path:
    """One PNG with every outfit in a grid (front view)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(len(outfits), 6)
    rows = int(np.ceil(len(outfits) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols, 4.0 * rows))
    axes = np.atleast_1d(axes).ravel()
    for ax, o in zip(axes, outfits, strict=False):
        draw_meshes(ax, outfit_meshes(o), view)
        ax.set_title(o.name, fontsize=7)
    for ax in axes[len(outfits):]:
        ax.axis("off")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
