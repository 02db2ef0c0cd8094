"""Speed of the SMLN step on a synthetic 2-layer outfit (tubes around a cylinder body).

Measures, with 1 and 2 torch threads: the median ms/frame of one inference step (graph build + network +
repulsion layer) on a ~5k-vertex 2-layer outfit around a 12k-vertex body, the share of each stage, and the
time of one training step (forward, a simple physics loss, backward, Adam step) on a ~1.5k-vertex outfit.
Prints JSON (and writes it with ``--json OUT``).

    python bench/rollout_speed.py [--json OUT] [--vertices N] [--repeats R]

The scene is synthetic for now; switch to the real outfits once ``smln.garments`` ships them.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time

import torch

from smln.graph.synthetic import cylinder_body, rigid_lbs, sway_motion, tube_outfit
from smln.losses.gravity import gravity_energy
from smln.losses.inertia import inertia_energy
from smln.losses.rest import ClothRest
from smln.losses.stretch import stretch_energy
from smln.model import SMLN, SMLNConfig


def _scene(vertices: int, body_rings: int = 100, frames: int = 4):
    """2-layer tube outfit of about ``vertices`` vertices (2 cm-ish spacing) on a 12k-vertex body."""
    per_layer = vertices / 2
    n_around = max(8, int(round(math.sqrt(per_layer * 1.6))))
    n_rings = max(3, int(round(per_layer / n_around)))
    height = 0.02 * n_rings
    cloth = tube_outfit(radii=(0.12, 0.126), height=height, n_around=n_around, n_rings=n_rings, z0=0.2)
    bv, bf = cylinder_body(n_around=120, n_rings=body_rings)
    tr = sway_motion(frames)
    return cloth, rigid_lbs(torch.as_tensor(bv), tr), rigid_lbs(cloth.rest_vertices, tr)


def _median_ms(fn, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(1e3 * (time.perf_counter() - t))
    return statistics.median(ts)


def inference(model: SMLN, vertices: int, repeats: int) -> dict:
    cloth, body, xs = _scene(vertices)
    topo = model.make_topology(cloth)
    model.eval()
    args = (xs[0], xs[1], body[1], body[2], xs[2])
    with torch.no_grad():
        g = topo.build(*args)
        p, _, ex = model(g, topo)
        x_hat = ex["x_hat"]
        from smln.geometry import vertex_normals

        build = _median_ms(lambda: topo.build(*args), repeats)
        total = _median_ms(lambda: model(topo.build(*args), topo), repeats)
        forward = _median_ms(lambda: model(g, topo), repeats)
        rep = _median_ms(
            lambda: model.repulsion(g.x_cur, x_hat, vertex_normals(x_hat, topo.faces), g.repulsion_pairs), repeats
        )
    net = max(forward - rep, 0.0)
    s = build + forward
    return {
        "vertices": cloth.num_vertices,
        "body_vertices": int(body.shape[1]),
        "mesh_edges": int(topo.mesh_edges.shape[1]),
        "virtual_edges": int(g.virtual_edges.shape[1]),
        "body_edges": int(g.body_receivers.numel()),
        "anchor_nodes": [lv.num_nodes for lv in topo.levels],
        "anchor_edges": [int(lv.edges.shape[1]) for lv in topo.levels],
        "ms_per_frame": round(total, 2),
        "ms_graph_build": round(build, 2),
        "ms_network": round(net, 2),
        "ms_repulsion": round(rep, 2),
        "share": {k: round(v / s, 3) for k, v in (("graph_build", build), ("network", net), ("repulsion", rep))},
    }


def training_step(model: SMLN, vertices: int, repeats: int) -> dict:
    cloth, body, xs = _scene(vertices)
    topo = model.make_topology(cloth)
    rest = ClothRest.from_cloth(cloth)
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step() -> None:
        g = topo.build(xs[0], xs[1], body[1], body[2], xs[2])
        _, _, ex = model(g, topo)
        x = ex["x_next"]
        loss = stretch_energy(x, rest) + gravity_energy(x, rest) + inertia_energy(xs[0], xs[1], x, rest, 1 / 30)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()

    return {"vertices": cloth.num_vertices, "ms_per_step": round(_median_ms(step, repeats), 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results here too")
    ap.add_argument("--vertices", type=int, default=5000, help="inference outfit size (2 layers)")
    ap.add_argument("--train-vertices", type=int, default=1500, help="training outfit size (2 layers)")
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    torch.manual_seed(0)
    cfg = SMLNConfig()
    out: dict = {"config": cfg.to_dict(), "torch": torch.__version__, "machine": platform.processor() or "cpu"}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        model = SMLN(cfg)
        out[f"threads_{threads}"] = {
            "inference": inference(model, args.vertices, args.repeats),
            "training": training_step(model, args.train_vertices, max(5, args.repeats // 2)),
        }
    text = json.dumps(out, indent=2)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
