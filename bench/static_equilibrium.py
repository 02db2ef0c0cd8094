"""Benchmark: the network's equilibrium on a still body against the minimiser of its own training loss.

The body is held at one frame of a clip (``--frame``) for ``--frames`` frames. The garments start from skinning and
are stepped (a) by the network (``smln.rollout.rollout``, the shipped settle step) and (b) by the reference
L-BFGS solver of the same per-step loss (``smln.solver.solver_rollout``). Nothing moves, so both should come to
rest; what differs at the last frame is how well the network found the loss's minimum. Reported per method:
mean |edge strain| (the metric), its signed mean, the stretch and compression parts, median and 90th percentile,
L-Coll and H-Coll, the training loss of the state at rest (x_prev = x_cur = x_next = x: no inertia, no
friction; the lower, the closer to the loss's minimum) and the per-edge correlation of the network's |strain|
with the solver's (1 = the same pattern, 0 = unrelated).

Run: ``python bench/static_equilibrium.py [--checkpoint checkpoints/full] [--outfit tshirt_jacket]
[--motion 05_01_walk] [--frame 0] [--frames 30] [--json OUT]`` (about 2 minutes on one core: the solver's 60
L-BFGS iterations per frame dominate).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from smln.checkpoint import load_checkpoint
from smln.data_sampling import make_scene
from smln.geometry import set_threads
from smln.losses import BodyStep, LossWeights, total_loss
from smln.rollout import rollout
from smln.solver import solver_rollout


def edge_strain(x: np.ndarray, edges: np.ndarray, rest_length: np.ndarray) -> np.ndarray:
    """(E,) signed edge strain l / l_rest - 1 of positions ``x`` (V, 3) m, ``edges`` (E, 2), ``rest_length`` (E,) m."""
    return np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / rest_length - 1.0


def strain_summary(s: np.ndarray) -> dict[str, float]:
    """Statistics (in %) of signed edge strains ``s`` (E,)."""
    a = np.abs(s)
    return {"strain_mean": 100 * float(a.mean()), "strain_signed": 100 * float(s.mean()),
            "stretch": 100 * float(np.clip(s, 0, None).mean()), "compression": 100 * float(np.clip(-s, 0, None).mean()),
            "strain_median": 100 * float(np.median(a)), "strain_p90": 100 * float(np.percentile(a, 90))}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="checkpoints/full")
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--motion", default="05_01_walk")
    p.add_argument("--frame", type=int, default=0, help="the clip's frame the body is held at")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json")
    args = p.parse_args(argv)
    set_threads(args.threads)
    scene = make_scene(args.outfit, "female_average", args.motion, edge_length=0.035, max_frames=args.frame + 1)
    n, f = args.frames, args.frame
    still = SimpleNamespace(vertices=scene.body.vertices[f:f + 1].repeat(n, 1, 1),
                            transforms=scene.body.transforms[f:f + 1].repeat(n, 1, 1, 1),
                            faces=scene.body.faces, num_frames=n)
    model, _ = load_checkpoint(args.checkpoint)
    net = list(rollout(model, scene.cloth, (still.vertices, still.transforms), still.faces, num_frames=n))[-1]
    ref = list(solver_rollout(scene.cloth, still, num_frames=n))[-1]
    edges, l0 = scene.rest.edges.numpy(), scene.rest.rest_length.numpy()
    body = BodyStep.from_vertices(still.vertices[0], still.vertices[0], still.faces)

    def rest_loss(x: np.ndarray) -> tuple[float, dict[str, float]]:
        xt = torch.as_tensor(x)
        with torch.no_grad():
            loss, terms = total_loss(xt, xt, xt, body, scene.rest, LossWeights.training())
        return float(loss), {k: float(v) for k, v in terms.items()}

    out: dict = {"checkpoint": args.checkpoint, "outfit": args.outfit, "motion": args.motion, "frame": f, "frames": n}
    skinned = scene.skinned[f].numpy()
    for name, x, metrics in (("skinning", skinned, None), ("network", net.garment_positions, net.metrics),
                             ("solver", ref.garment_positions, ref.metrics)):
        row = strain_summary(edge_strain(x, edges, l0))
        row["loss_at_rest"], row["loss_terms"] = rest_loss(x)
        if metrics is not None:
            row.update(l_coll=metrics["l_coll"], h_coll=metrics["h_coll"])
        out[name] = row
    a_net, a_ref = (np.abs(edge_strain(fr.garment_positions, edges, l0)) for fr in (net, ref))
    out["per_edge_correlation"] = float(np.corrcoef(a_net, a_ref)[0, 1])
    print(f"{args.outfit} on {args.motion} frame {f}, held {n} frames (strain in %):")
    for name in ("skinning", "network", "solver"):
        r = out[name]
        coll = f"  L-Coll {r['l_coll']:.2f}  H-Coll {r['h_coll']:.2f}" if "l_coll" in r else ""
        print(f"  {name:8s} |strain| {r['strain_mean']:.2f} (signed {r['strain_signed']:+.2f}, stretch "
              f"{r['stretch']:.2f}, compression {r['compression']:.2f}, median {r['strain_median']:.2f}, "
              f"p90 {r['strain_p90']:.1f}){coll}  loss {r['loss_at_rest']:.3f}")
    print(f"  per-edge correlation of |strain|, network vs solver: {out['per_edge_correlation']:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
