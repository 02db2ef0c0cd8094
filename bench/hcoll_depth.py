"""Benchmark: where does H-Coll come from? Depth of the body penetrations, per garment layer.

H-Coll counts a cloth vertex inside the body when its signed distance along its nearest body vertex's normal is
negative (the metric of ``smln eval``). This script rolls a checkpoint out (and, for reference, the rigidly skinned
garment) and prints per layer: H-Coll %, the median and 90th percentile depth of the penetrating vertices (mm), the
share of them shallower than 2 mm, and the share of all the layer's vertices within 0-3 mm of the body (the band
the body penalty's clearance holds resting cloth in). Shallow penetrations next to a full contact band mean the
model's step errors carry resting cloth through the body; deep ones mean whole panels are caught inside it.
A checkpoint's frames that fell back to skinning are left out (the skinning row has every frame).

Run: ``python bench/hcoll_depth.py --checkpoints shipped=checkpoints/full [other=PATH ...] [--outfit tshirt_jacket]
[--motion 05_01_walk] [--frames 150] [--json OUT]`` (about 40 s per checkpoint and 150 frames on one core).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from smln.body import DEFAULT_SHAPE
from smln.checkpoint import load_checkpoint
from smln.data_sampling import make_scene
from smln.geometry import PointTree, build_tree, set_threads, signed_distance_along_normals, vertex_normals
from smln.rollout import rollout

SHALLOW = 2e-3
"""Depth below which a penetration counts as shallow, meters."""

CONTACT_BAND = 3e-3
"""Distance from the body within which a vertex counts as resting on it, meters (the default clearance)."""


def penetration_profile(d: np.ndarray, layer_index: np.ndarray) -> dict[int, dict[str, float]]:
    """Per-layer summary of signed body distances.

    Args:
        d: (T, V) signed distances of the cloth vertices to the body along the nearest body normal, meters
            (negative = inside).
        layer_index: (V,) int layer of each vertex, 0 = innermost.

    Returns:
        layer -> ``h_coll`` (% of vertex-frames with d < 0), ``depth_p50_mm`` / ``depth_p90_mm`` (of those),
        ``shallow`` (% of them with depth < :data:`SHALLOW`), ``contact_band`` (% of all vertex-frames with
        0 <= d < :data:`CONTACT_BAND`). Depths are 0 and ``shallow`` NaN for a layer that never penetrates.
    """
    out: dict[int, dict[str, float]] = {}
    for layer in np.unique(layer_index):
        dl = d[:, layer_index == layer]
        depth = -dl[dl < 0]
        any_pen = depth.size > 0
        out[int(layer)] = {
            "h_coll": float(100.0 * (dl < 0).mean()),
            "depth_p50_mm": float(1e3 * np.median(depth)) if any_pen else 0.0,
            "depth_p90_mm": float(1e3 * np.percentile(depth, 90)) if any_pen else 0.0,
            "shallow": float(100.0 * (depth < SHALLOW).mean()) if any_pen else float("nan"),
            "contact_band": float(100.0 * ((dl >= 0) & (dl < CONTACT_BAND)).mean()),
        }
    return out


def body_distances(x: np.ndarray, body: torch.Tensor, body_faces: torch.Tensor | None = None,
                   normals: torch.Tensor | None = None, tree: PointTree | None = None) -> np.ndarray:
    """(V,) signed distance of cloth positions ``x`` (V, 3) to the body (Vb, 3) along its vertex normals, m.

    Pass the frame's ``normals`` (Vb, 3) and KD-``tree`` to reuse them across queries; else ``body_faces``."""
    if normals is None:
        normals = vertex_normals(body, body_faces)
    _, d = signed_distance_along_normals(torch.as_tensor(x), body, normals, tree=tree)
    return d.numpy()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoints", nargs="+", required=True, help="LABEL=PATH ...")
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--motion", default="05_01_walk")
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--edge-length", type=float, default=0.035)
    p.add_argument("--json", type=Path)
    a = p.parse_args()
    set_threads(1)
    torch.set_num_threads(1)
    scene = make_scene(a.outfit, DEFAULT_SHAPE, a.motion, edge_length=a.edge_length, max_frames=a.frames)
    layers = scene.cloth.layer_index.numpy()
    faces = scene.body.faces
    # per frame once: the body's normals and KD-tree, shared by the skinned garment and every checkpoint
    bodies = scene.body.vertices[: scene.num_frames]
    normals = [vertex_normals(b, faces) for b in bodies]
    trees = [build_tree(b) for b in bodies]
    skinned_d = [body_distances(scene.skinned[t].numpy(), b, normals=normals[t], tree=trees[t])
                 for t, b in enumerate(bodies)]
    report: dict[str, dict[int, dict[str, float]]] = {}
    for spec in a.checkpoints:
        label, _, path = spec.partition("=")
        model, _ = load_checkpoint(path)
        model_d = [body_distances(fr.garment_positions, bodies[fr.index], normals=normals[fr.index],
                                  tree=trees[fr.index])
                   for fr in rollout(model, scene.cloth, scene.body, faces, num_frames=scene.num_frames,
                                     fallback=True)
                   if not fr.fallback]
        report[label] = penetration_profile(np.stack(model_d), layers)
    report["skinning"] = penetration_profile(np.stack(skinned_d), layers)
    print(f"{a.outfit} on {a.motion}, {scene.num_frames} frames (a checkpoint's fallback frames left out)")
    for label, per_layer in report.items():
        for layer, r in per_layer.items():
            print(f"  {label:12s} layer {layer}: H-Coll {r['h_coll']:5.2f} %  depth p50 {r['depth_p50_mm']:5.1f} mm "
                  f"p90 {r['depth_p90_mm']:5.1f} mm  shallow (<2 mm) {r['shallow']:3.0f} %  "
                  f"within 0-3 mm {r['contact_band']:4.1f} %")
    if a.json:
        a.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
