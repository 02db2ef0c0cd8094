"""Benchmark: does minimising the training loss drive the paper's metrics down? Loss weights vs the L-BFGS solver.

The learned model can at best match the per-frame minimiser of the loss it is trained on (``smln.solver``). This
script runs that minimiser with several repulsion weights λr, body-collision weights and repulsion pair radii on
one scene and reports L-Coll, H-Coll and mean edge strain, averaged over the predicted frames (the first two
frames are the skinned start). It is the evidence behind :meth:`smln.losses.LossWeights.training` and
:data:`smln.losses.repulsion.PAIR_RADIUS`.

Run: ``python bench/solver_weights.py [--outfit tshirt_jacket] [--motion 05_01_walk] [--frames 25]
[--json OUT] [--markdown OUT]`` (about 75 s per configuration at 3.5 cm edges on one core).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from smln.data_sampling import make_scene
from smln.geometry import set_threads
from smln.losses import LossWeights
from smln.solver import solver_rollout

CONFIGS = [
    # (repulsion weight, body collision weight, pair radius m, body clearance eps m)
    (1e3, 1e4, 0.02, 3e-3),  # the paper's λr with session 1-2's radius
    (1e4, 1e4, 0.02, 3e-3),
    (1e4, 1e4, 0.04, 3e-3),  # the training default
    (3e4, 1e4, 0.04, 3e-3),
    (1e4, 3e4, 0.04, 3e-3),
    (1e4, 1e4, 0.04, 4.5e-3),  # a wider body clearance (session 6)
    (1e4, 1e4, 0.04, 6e-3),
]


def run_config(scene, frames: int, repulsion: float, collision: float, radius: float, eps: float = 3e-3
               ) -> dict[str, float]:
    """Mean metrics of the solver's predicted frames (index >= 2) for one weight setting."""
    t0 = time.perf_counter()
    rows = [fr.metrics for fr in solver_rollout(scene.cloth, scene.body, num_frames=frames,
                                                weights=LossWeights(repulsion=repulsion, collision=collision,
                                                                   collision_eps=eps),
                                                pair_radius=radius)][2:]
    return {
        "repulsion": repulsion, "collision": collision, "pair_radius": radius, "collision_eps": eps,
        "l_coll": float(np.mean([r["l_coll"] for r in rows])),
        "h_coll": float(np.mean([r["h_coll"] for r in rows])),
        "strain_mean_pct": 100 * float(np.mean([r["strain_mean"] for r in rows])),
        "l_coll_last": rows[-1]["l_coll"], "h_coll_last": rows[-1]["h_coll"],
        "seconds": time.perf_counter() - t0,
    }


def main(argv: list[str] | None = None) -> list[dict[str, float]]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--motion", default="05_01_walk")
    p.add_argument("--shape", default="female_average")
    p.add_argument("--frames", type=int, default=25)
    p.add_argument("--edge-length", type=float, default=0.035)
    p.add_argument("--json")
    p.add_argument("--markdown")
    args = p.parse_args(argv)
    set_threads(1)
    scene = make_scene(args.outfit, args.shape, args.motion, edge_length=args.edge_length, max_frames=args.frames)
    rows = []
    for rep, col, radius, eps in CONFIGS:
        rows.append(run_config(scene, args.frames, rep, col, radius, eps))
        print(json.dumps(rows[-1]), flush=True)
    lines = [
        f"L-BFGS minimiser of the training loss, {args.outfit} / {args.motion} / {args.shape}, frames 2-"
        f"{args.frames - 1}, {args.edge_length * 100:.1f} cm edges ({platform.processor() or platform.machine()}, "
        f"torch {torch.__version__}):",
        "",
        "| λr (repulsion) | body collision | pair radius (cm) | body clearance (mm) | L-Coll % | H-Coll % "
        "| mean strain % | last frame L / H % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['repulsion']:.0e} | {r['collision']:.0e} | {100 * r['pair_radius']:.0f} "
                     f"| {1e3 * r['collision_eps']:.1f} "
                     f"| {r['l_coll']:.2f} | {r['h_coll']:.2f} | {r['strain_mean_pct']:.2f} "
                     f"| {r['l_coll_last']:.2f} / {r['h_coll_last']:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1))
    if args.markdown:
        Path(args.markdown).write_text(text)
    return rows


if __name__ == "__main__":
    main()
