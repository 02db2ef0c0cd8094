"""Speed of the SMLN step on the real outfits (or a synthetic scene with ``--synthetic``).

Measures, with 1 and 2 torch threads (each median of ``--repeats`` timings):

- inference: median ms/frame of a full :func:`smln.rollout.rollout` frame (graph build + network + repulsion
  layer + per-frame metrics and divergence checks; untrained weights, divergence thresholds off) on a
  2-layer ~5k-vertex outfit (``tshirt_jacket`` at 2 cm, ~5k vertices) and a 3-layer outfit
  (``tanktop_tshirt_jacket``, ~6.5k vertices) on the ``02_01_walk`` clip, plus the per-stage times
  and shares (graph build, network, repulsion layer, metrics) measured on one frame's state;
- training: median time of one training step (graph build, forward, the full loss of
  :func:`smln.losses.total_loss`, backward, gradient clipping, Adam) on a coarse 2-layer outfit
  (``tshirt_jacket`` at 3.5 cm).

Prints JSON (and writes it with ``--json OUT``), including the 1-minute load average before and after (the
machine is shared: compare medians taken at similar load).

    python bench/rollout_speed.py [--json OUT] [--repeats R] [--threads 1 2] [--synthetic]
                                   [--precision float32 bfloat16] [--compile] [--model-config TRAIN_CONFIG]

With ``--precision bfloat16`` (default on CPUs with AMX / AVX512-BF16) the inference rows are repeated with the
processor in bfloat16 (:mod:`smln.model.precision`) under ``inference_bfloat16``; with ``--compile`` once more per
precision with the processor through ``torch.compile`` (:mod:`smln.model.compiled`) under ``inference_compiled`` /
``inference_bfloat16_compiled``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import time
from typing import Any

import numpy as np
import torch

from smln.cloth import Cloth
from smln.geometry import set_threads, vertex_normals
from smln.losses import BodyStep, ClothRest, layer_pairs, total_loss
from smln.metrics import frame_metrics
from smln.model import SMLN, SMLNConfig
from smln.model.compiled import with_compiled_processor
from smln.model.precision import native_bfloat16, with_processor_dtype
from smln.rollout import rollout

INFER_OUTFITS = ("tshirt_jacket", "tanktop_tshirt_jacket")  # 2 layers ~4.8k vertices, 3 layers ~6.4k
TRAIN_OUTFIT = "tshirt_jacket"
MOTION = "02_01_walk"


class Scene:
    """An outfit on a body clip: ``cloth``, ``body`` (T, Vb, 3), ``transforms``, ``faces`` (Fb, 3)."""

    def __init__(self, name: str, cloth: Cloth, body: torch.Tensor, transforms: torch.Tensor, faces: torch.Tensor):
        self.name, self.cloth, self.body, self.transforms, self.faces = name, cloth, body, transforms, faces

    @property
    def vertices(self) -> torch.Tensor:  # rollout() reads .vertices / .transforms
        return self.body


def real_scene(outfit: str, edge_length: float, frames: int) -> Scene:
    from smln.body import load_body
    from smln.garments import build_outfit
    from smln.motion import load_body_sequence

    body = load_body("female_average")
    seq = load_body_sequence(MOTION, body, max_frames=frames)
    cloth = build_outfit(outfit, shape="female_average", edge_length=edge_length).to_cloth()
    return Scene(f"{outfit}@{edge_length}", cloth, seq.vertices, seq.transforms, seq.faces)


def synthetic_scene(vertices: int, frames: int) -> Scene:
    """2-layer tube outfit of about ``vertices`` vertices (2 cm-ish spacing) around a 12k-vertex cylinder."""
    from smln.graph.synthetic import cylinder_body, rigid_lbs, sway_motion, tube_outfit

    per_layer = vertices / 2
    n_around = max(8, int(round(math.sqrt(per_layer * 1.6))))
    n_rings = max(3, int(round(per_layer / n_around)))
    cloth = tube_outfit(radii=(0.12, 0.126), height=0.02 * n_rings, n_around=n_around, n_rings=n_rings, z0=0.2)
    bv, bf = cylinder_body(n_around=120, n_rings=100)
    tr = sway_motion(frames)
    return Scene(f"synthetic_tubes_{cloth.num_vertices}", cloth, rigid_lbs(torch.as_tensor(bv), tr), tr,
                 torch.as_tensor(bf))


def _median_ms(fn, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(1e3 * (time.perf_counter() - t))
    return statistics.median(ts)


def _skinned(scene: Scene, n: int) -> torch.Tensor:
    from smln.body import lbs

    c = scene.cloth
    return lbs(c.rest_vertices.float(), c.skin_indices, c.skin_weights, torch.as_tensor(scene.transforms[:n]).float())


def inference(model: SMLN, scene: Scene, repeats: int, precision: str = "float32", compiled: bool = False
              ) -> dict[str, Any]:
    """ms/frame of real rollout frames, and per-stage medians on one frame's state (processor in ``precision``,
    through torch.compile if ``compiled``: the compilation falls in the warm-up frame and the first forward)."""
    model.eval()
    frames = repeats + 4
    ms = []
    t_prev = time.perf_counter()
    # an untrained model strains the cloth: thresholds off so every frame takes the normal path (a rejected
    # frame would compute its metrics twice); fallback only guards against non-finite positions
    for fr in rollout(model, scene.cloth, scene, scene.faces, num_frames=frames, fallback=True,
                      max_distance=1e9, max_strain=1e9, precision=precision, compiled=compiled):
        t = time.perf_counter()
        if fr.index >= 3:  # frames 0, 1 are skinned; frame 2 warms up
            ms.append(1e3 * (t - t_prev))
        t_prev = t
    topo = model.make_topology(scene.cloth)
    rest = ClothRest.from_cloth(scene.cloth)
    xs = _skinned(scene, 3)
    body = torch.as_tensor(scene.body).float()
    args = (xs[0], xs[1], body[1], body[2], xs[2])
    faces_np = np.asarray(scene.faces, dtype=np.int64)
    faces_t = torch.as_tensor(faces_np)
    model = with_processor_dtype(model, precision)
    if compiled:
        model = with_compiled_processor(model)

    def build_graph() -> Any:  # the rollout computes the body normals per step too (timed with the build)
        normals = vertex_normals(body[2], faces_t) if topo.body_normals else None
        return topo.build(*args, body_normals_next=normals)

    with torch.no_grad():
        g = build_graph()
        _, _, ex = model(g, topo)
        x_hat = ex["x_hat"]
        build = _median_ms(build_graph, repeats)
        forward = _median_ms(lambda: model(g, topo), repeats)
        rep = _median_ms(
            lambda: model.repulsion(g.x_cur, x_hat, vertex_normals(x_hat, topo.faces), g.repulsion_pairs), repeats
        )
        metrics = _median_ms(lambda: frame_metrics(ex["x_next"], body[2], rest, body_faces=faces_np), repeats)
    net = max(forward - rep, 0.0)
    s = build + forward + metrics
    return {
        "scene": scene.name,
        "precision": precision,
        "compiled": compiled,
        "layers": scene.cloth.num_layers,
        "vertices": scene.cloth.num_vertices,
        "body_vertices": int(body.shape[1]),
        "mesh_edges": int(topo.mesh_edges.shape[1]),
        "virtual_edges": int(g.virtual_edges.shape[1]),
        "body_edges": int(g.body_receivers.numel()),
        "anchor_nodes": [lv.num_nodes for lv in topo.levels],
        "anchor_edges": [int(lv.edges.shape[1]) for lv in topo.levels],
        "ms_per_frame_rollout": round(statistics.median(ms), 2),
        "ms_per_frame_step": round(build + forward, 2),
        "ms_graph_build": round(build, 2),
        "ms_network": round(net, 2),
        "ms_repulsion": round(rep, 2),
        "ms_metrics": round(metrics, 2),
        "share": {k: round(v / s, 3) for k, v in
                  (("graph_build", build), ("network", net), ("repulsion", rep), ("metrics", metrics))},
    }


def training_step(model: SMLN, scene: Scene, repeats: int) -> dict[str, Any]:
    """Median ms of one training step (build, forward, total loss, backward, clip, Adam)."""
    topo = model.make_topology(scene.cloth)
    rest = ClothRest.from_cloth(scene.cloth)
    xs = _skinned(scene, 3)
    body = torch.as_tensor(scene.body).float()
    bstep = BodyStep.from_vertices(body[1], body[2], torch.as_tensor(scene.faces, dtype=torch.int64))
    pairs = layer_pairs(xs[1], rest)
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step() -> None:
        g = topo.build(xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=bstep.normals_next)
        _, _, ex = model(g, topo)
        loss, _ = total_loss(xs[0], xs[1], ex["x_next"], bstep, rest, pairs=pairs)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()

    ms = _median_ms(step, repeats)
    return {"scene": scene.name, "vertices": scene.cloth.num_vertices, "ms_per_step": round(ms, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results here too")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--synthetic", action="store_true", help="synthetic tubes on a cylinder instead of real outfits")
    ap.add_argument("--vertices", type=int, default=5000, help="--synthetic: inference outfit size (2 layers)")
    ap.add_argument("--train-vertices", type=int, default=1500, help="--synthetic: training outfit size")
    ap.add_argument("--precision", nargs="+", choices=["float32", "bfloat16"],
                    help="inference precisions (default: float32, plus bfloat16 on CPUs with native bfloat16)")
    ap.add_argument("--compile", action="store_true",
                    help="also time every inference precision with the processor through torch.compile "
                         "(rows inference_compiled / inference_bfloat16_compiled; smln.model.compiled)")
    ap.add_argument("--model-config", help="a `smln train --config` JSON file: time the architecture of its `model` "
                                           "entry (e.g. docs/results/r29_mlp2_config.json) instead of the default")
    args = ap.parse_args()
    precisions = args.precision or (["float32", "bfloat16"] if native_bfloat16() else ["float32"])
    torch.manual_seed(0)
    cfg = SMLNConfig()
    if args.model_config:
        with open(args.model_config) as f:
            cfg = SMLNConfig.from_dict({**cfg.to_dict(), **json.load(f).get("model", {})})
    frames = args.repeats + 4
    if args.synthetic:
        infer = [synthetic_scene(args.vertices, frames)]
        train = synthetic_scene(args.train_vertices, 4)
    else:
        infer = [real_scene(o, 0.02, frames) for o in INFER_OUTFITS]
        train = real_scene(TRAIN_OUTFIT, 0.035, 4)
    out: dict[str, Any] = {
        "config": cfg.to_dict(), "torch": torch.__version__, "machine": platform.processor() or "cpu",
        "cpus": os.cpu_count(), "load_before": round(os.getloadavg()[0], 2),
    }
    for threads in args.threads:
        set_threads(threads)
        model = SMLN(cfg)
        out[f"threads_{threads}"] = {
            "inference": [inference(model, s, args.repeats) for s in infer],
            "training": training_step(SMLN(cfg), train, max(5, args.repeats // 2)),
        }
        if "bfloat16" in precisions:
            out[f"threads_{threads}"]["inference_bfloat16"] = [
                inference(model, s, args.repeats, "bfloat16") for s in infer
            ]
        if args.compile:
            for prec in precisions:
                key = "inference_compiled" if prec == "float32" else f"inference_{prec}_compiled"
                out[f"threads_{threads}"][key] = [inference(model, s, args.repeats, prec, compiled=True)
                                                  for s in infer]
    out["load_after"] = round(os.getloadavg()[0], 2)
    text = json.dumps(out, indent=2)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
