"""Render a few frames of each method side by side (matplotlib, no GPU) for docs/RESULTS.md.

    python scripts/render_rollout_frames.py --outfit tshirt_jacket --motion 05_01_walk --frames 20 45 70 \
        --out docs/results/frames_tshirt_jacket.png

Rows are methods (skinning and every checkpoint found in ``--checkpoints``, or the ``--models LABEL=PATH`` given),
columns the requested frames; body in grey, layers in colour, inter-layer penetrating vertices in red.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from smln.data_sampling import make_scene
from smln.evaluate import method_frames
from smln.garments.render import BODY_COLOUR, LAYER_COLOURS, VIEWS, draw_meshes
from smln.geometry import set_threads


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--motion", default="05_01_walk")
    p.add_argument("--shape", default="female_average")
    p.add_argument("--frames", type=int, nargs="+", default=[20, 45, 70])
    p.add_argument("--checkpoints", default="checkpoints")
    p.add_argument("--models", nargs="+", metavar="LABEL=PATH",
                   help="rows to draw instead of the variants found in --checkpoints, "
                        "e.g. old=runs/a/best new=runs/b/best")
    p.add_argument("--edge-length", type=float, default=0.035)
    p.add_argument("--view", default="front", choices=["front", "side", "back"])
    p.add_argument("--out", required=True)
    a = p.parse_args()
    set_threads(2)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from smln.checkpoint import load_checkpoint

    scene = make_scene(a.outfit, a.shape, a.motion, edge_length=a.edge_length, max_frames=max(a.frames) + 1)
    n = scene.num_frames
    a.frames = sorted({min(t, n - 1) for t in a.frames})
    methods: list[tuple[str, object | None]] = [("skinning", None)]
    if a.models:
        for spec in a.models:
            label, sep, path = spec.partition("=")
            if not sep or not label or not path:
                p.error(f"--models takes LABEL=PATH, got {spec!r}")
            methods.append((label, load_checkpoint(path)[0]))
    else:
        for v in ("full", "no_repulsion_layer", "baseline"):
            path = Path(a.checkpoints) / v
            if path.exists():
                methods.append((v, load_checkpoint(path)[0]))
    faces = scene.cloth.faces.numpy()
    layer_of_face = scene.cloth.layer_index[scene.cloth.faces[:, 0]].numpy()
    fig, axes = plt.subplots(len(methods), len(a.frames), figsize=(3.2 * len(a.frames), 4.2 * len(methods)))
    axes = np.atleast_2d(axes)
    for row, (name, model) in enumerate(methods):
        frames = {fr.index: fr for fr in method_frames("model" if model else name, model, scene, n)}
        for col, t in enumerate(a.frames):
            fr = frames[t]
            meshes = [(fr.body_vertices, scene.body.faces.numpy(), BODY_COLOUR)]
            for k in range(scene.cloth.num_layers):
                meshes.append((fr.garment_positions, faces[layer_of_face == k], LAYER_COLOURS[k % 4]))
            ax = axes[row, col]
            draw_meshes(ax, meshes, a.view)
            pen = fr.layer_penetration
            if pen.any():
                pts = fr.garment_positions[pen]
                sx = np.asarray(VIEWS[a.view][0], dtype=np.float64)  # the same screen axis as draw_meshes
                ax.scatter(pts @ sx, pts[:, 2], s=2, c="red")
            label = f"{name}  t={t}" + ("  (fallback)" if fr.fallback else "")
            ax.set_title(f"{label}\nL-Coll {fr.metrics['l_coll']:.1f}%  H-Coll {fr.metrics['h_coll']:.1f}%", fontsize=8)
    fig.tight_layout()
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=80)
    print(a.out)


if __name__ == "__main__":
    main()
