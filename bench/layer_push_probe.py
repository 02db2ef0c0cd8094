"""Diagnostic: does the repulsion layer push the outer layer's penetrating vertices, and which way?

    python bench/layer_push_probe.py --checkpoint checkpoints/full --outfit tshirt_jacket --shape male_average \\
        --motion 09_06_run --frames 150

Rolls the checkpoint out (fallback on, frames that fell back and the first two skipped) and, per frame, pairs each
vertex of the outermost layer with its nearest vertex of the layer beneath at the frame's positions, the L-Coll
test's pairing (not the layer's own pairs, which are found at the step before). Against that vertex's normal it
reports, averaged over frames: the share of outer vertices the layer pushes at all, the share behind the layer
beneath, the share of pushed vertices pushed outward, the share of the vertices behind that are pushed, and of those
the share pushed outward; the median push (m/frame²), the median depth of the vertices behind (m), and the share of
them farther than the graph's virtual-edge radius from the layer beneath (beyond its hem, not through it). Then, from
the layer's own pairs of the step (a forward hook): the share of the vertices behind that are in any pair, the share
of those whose pairs all read them at least the layer's threshold in front (so it does not push them), and the
median of their closest pair's E_r (m). Two-layer outfits only.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
from scipy.spatial import cKDTree

from smln.checkpoint import load_checkpoint
from smln.data_sampling import make_scene
from smln.geometry import set_threads
from smln.geometry.mesh import vertex_normals
from smln.rollout import rollout

FIGURES = ("pushed", "behind", "pushed_outward", "behind_pushed", "behind_pushed_outward", "median_push",
           "median_depth", "behind_far", "behind_paired", "behind_paired_read_clear", "behind_median_pair_distance")


def frame_figures(x: np.ndarray, repulsion: np.ndarray, faces: torch.Tensor, inner: slice, outer: slice,
                  pairs: np.ndarray | None = None, signed_distance: np.ndarray | None = None,
                  threshold: float = 0.005, far: float = 0.05) -> np.ndarray:
    """The :data:`FIGURES` of one frame (NaN where a share has no vertex to count).

    Args:
        x: (V, 3) garment positions, m. repulsion: (V, 3) the layer's acceleration, m/frame².
        faces: (F, 3) garment triangles. inner, outer: the two layers' vertex slices.
        pairs: (2, P) the layer's own pairs of the step (outer i, inner j), or None (the last three figures NaN).
        signed_distance: (P,) each pair's E_r as the layer read it (m; at or above ``threshold`` it does not push).
        far: ``behind_far`` counts the vertices behind whose nearest inner vertex is farther than this (m; the
            graph's virtual-edge radius: such a vertex is in no pair of the layer, and lies beyond the inner
            layer's hem rather than through it: the vertex test's hem effect).
    """
    normals = vertex_normals(torch.as_tensor(x), faces).numpy()
    gap, nearest = cKDTree(x[inner]).query(x[outer])
    nearest = nearest + inner.start
    n = normals[nearest]
    signed = np.einsum("ij,ij->i", x[outer] - x[nearest], n)  # < 0: behind the layer beneath
    a = repulsion[outer]
    along = np.einsum("ij,ij->i", a, n)  # > 0: pushed outward
    magnitude = np.linalg.norm(a, axis=1)
    pushed, behind = magnitude > 0.0, signed < 0.0

    def share(mask: np.ndarray, of: np.ndarray) -> float:
        return float(mask[of].mean()) if of.any() else float("nan")

    own = [float("nan")] * 3
    if pairs is not None and signed_distance is not None:
        closest = np.full(x.shape[0], np.inf)  # per vertex, its pairs' smallest E_r (inf: in no pair)
        np.minimum.at(closest, pairs[0], signed_distance)
        closest = closest[outer]
        paired = np.isfinite(closest)
        own = [share(paired, behind), share(closest >= threshold, behind & paired),
               float(np.median(closest[behind & paired])) if (behind & paired).any() else float("nan")]
    return np.array([pushed.mean(), behind.mean(), share(along > 0, pushed), share(pushed, behind),
                     share(along > 0, pushed & behind),
                     float(np.median(magnitude[pushed])) if pushed.any() else float("nan"),
                     float(np.median(-signed[behind])) if behind.any() else float("nan"), share(gap > far, behind),
                     *own])


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="checkpoints/full")
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--shape", default="female_average")
    p.add_argument("--motion", default="05_01_walk")
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", help="write the figures to this file")
    args = p.parse_args(argv)
    set_threads(args.threads)
    torch.set_num_threads(args.threads)
    scene = make_scene(args.outfit, args.shape, args.motion, edge_length=0.035, max_frames=args.frames)
    if scene.cloth.num_layers != 2:
        raise SystemExit(f"{args.outfit} has {scene.cloth.num_layers} layers; the probe takes two-layer outfits")
    model, _ = load_checkpoint(args.checkpoint)
    inner, outer = scene.rest.layer_slices
    step: dict[str, np.ndarray] = {}  # the layer's pairs and their E_r at the latest step (a forward hook)

    def keep_pairs(_module, inputs, output) -> None:
        step["pairs"], step["signed"] = inputs[3].cpu().numpy(), output[1]["signed_distance"].cpu().numpy()

    hook = model.repulsion.register_forward_hook(keep_pairs) if model.config.use_repulsion_layer else None
    rows = []
    for f in rollout(model, scene.cloth, scene.body, scene.body.faces, num_frames=args.frames, fallback=True):
        if not f.fallback and f.index >= 2:
            rows.append(frame_figures(f.garment_positions, f.repulsion_acceleration, scene.cloth.faces, inner, outer,
                                      step.get("pairs"), step.get("signed"), model.repulsion.threshold,
                                      model.config.virtual_radius))
    if hook is not None:
        hook.remove()
    figures = dict(zip(FIGURES, np.nanmean(np.array(rows), axis=0).tolist(), strict=True))
    for name, value in figures.items():
        print(f"{name}: {value:.4g}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({**vars(args), "frames_used": len(rows), **figures}, fh, indent=1)
    return figures


if __name__ == "__main__":
    main()
