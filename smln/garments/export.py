"""Functions behind the CLI: the outfit table and exporting a dressed rest pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from smln.body import load_body
from smln.garments.garment import GarmentError
from smln.garments.library import DEFAULT_EDGE_LENGTH
from smln.garments.outfit import OUTFITS, build_outfit, outfit_split

EXPORT_FORMATS = (".obj", ".glb", ".ply")


def outfits_table(shape: str = "female_average", edge_length: float = DEFAULT_EDGE_LENGTH) -> list[dict]:
    """One row per registered outfit.

    Returns:
        dicts with ``name``, ``split``, ``layers`` (list of {"type", "vertices", "faces", "pinned"}),
        ``vertices`` and ``faces`` (totals) on ``shape`` at ``edge_length`` (m).
    """
    rows = []
    for name in OUTFITS:
        o = build_outfit(name, shape, edge_length)
        layers = [{"type": g.garment_type, "vertices": g.num_vertices, "faces": g.num_faces,
                   "pinned": int(g.pinned.sum())} for g in o.layers]
        rows.append({"name": name, "split": outfit_split(name), "layers": layers,
                     "vertices": sum(r["vertices"] for r in layers), "faces": sum(r["faces"] for r in layers)})
    return rows


def export_outfit(name: str, shape: str = "female_average", path: str | Path = "outfit.glb",
                  edge_length: float = DEFAULT_EDGE_LENGTH) -> Path:
    """Write the dressed rest pose (body + layers, T-pose, meters) as .obj, .glb or .ply.

    .glb keeps body and layers as separate named, coloured meshes; .obj/.ply get one merged mesh with
    per-vertex colours.
    """
    import trimesh

    from smln.garments.render import BODY_COLOUR, LAYER_COLOURS

    path = Path(path)
    if path.suffix.lower() not in EXPORT_FORMATS:
        raise GarmentError(f"unsupported export format {path.suffix!r}; use one of {', '.join(EXPORT_FORMATS)}")
    o = build_outfit(name, shape, edge_length)
    body = load_body(shape)
    parts = [("body", body.rest_vertices.numpy(), body.faces.numpy(), BODY_COLOUR)]
    parts += [(f"layer{i}_{g.name}", g.vertices, g.faces, LAYER_COLOURS[i % len(LAYER_COLOURS)])
              for i, g in enumerate(o.layers)]
    meshes = {}
    for n, v, f, rgb in parts:
        colour = np.tile(np.r_[np.asarray(rgb) * 255, 255].astype(np.uint8), (len(v), 1))
        meshes[n] = trimesh.Trimesh(v, f, vertex_colors=colour, process=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".glb":
        trimesh.Scene(meshes).export(path)
    else:
        trimesh.util.concatenate(list(meshes.values())).export(path)
    return path
