"""Diagnostic: the repulsion layer's garment stage read several ways, on the same checkpoint and clips.

    python bench/layer_pairing_probe.py --checkpoint checkpoints/full --outfits tshirt_jacket \\
        --motions 05_01_walk 09_06_run --frames 150 --json-dir runs/pairing

Each mode is an inference-time change of the full model's garment stage (weights untouched; the body stage and
the network's own prediction are kept):

- ``vertex``: ``repulsion_pairing = "vertex"``, as trained (paper Eq. 14): each outer vertex against its nearest
  inner vertex and that vertex's normal (the virtual edges of step t).
- ``off``: no garment stage (the network's ``p`` and the body stage only): how much of the layer-penetration
  figures the garment stage itself makes.
- ``surface``: each paired outer vertex against the closest point of the inner layer's *triangles* at step t
  (barycentric coordinates kept, the point and its interpolated normal moved to x̂), skipping a vertex whose
  closest point is on the inner layer's open boundary (beyond its hem, not behind it), as the point-to-triangle
  L-Coll reads it (:func:`smln.metrics.behind_surface`).
- ``deeper``: ``SMLNConfig.repulsion_pairing = "deeper"``: both readings per outer vertex, the one that reads it
  deeper pushes (a surface point on the hem or on the back of a fold is no reading).
- ``nearest``: ``SMLNConfig.repulsion_pairing = "nearest"`` (session 41): each paired outer vertex against the
  inner vertex nearest to its prediction at t+1 (the L-Coll metric's pairing) instead of its nearest at step t.
- ``vertex_body_guard``, ``deeper_body_guard``: those two readings, and the garment stage's push of a vertex with a
  body world edge loses its component toward the body (along its nearest body vertex's normal): the stage can no
  longer push a vertex squeezed between a fold of the layer beneath and the body into the body.

Writes one ``smln eval --json`` file per mode (method name = mode) with the point-to-triangle metrics, so that
``scripts/paired_variants.py A.json B.json --a surface --b vertex --key l_coll_surface`` pairs them.
"""

from __future__ import annotations

import argparse
import copy
import json
import types
from pathlib import Path

import torch

from smln.checkpoint import load_checkpoint
from smln.evaluate import apply_body_pairing, evaluate, resolve_names
from smln.geometry import set_threads
from smln.geometry.mesh import vertex_normals
from smln.model.smln import BODY_PAIRINGS, surface_partners

MODES = ("vertex", "off", "surface", "deeper", "nearest", "vertex_body_guard", "deeper_body_guard")


def _off_cascade(self, topology, graph, x_hat, free, a_start=None):
    """No garment stage: the body stage's push only (zeros without it)."""
    a = torch.zeros_like(x_hat) if a_start is None else a_start
    empty = torch.zeros(0, dtype=x_hat.dtype)
    return a, {"active_pairs": torch.zeros((2, 0), dtype=torch.long), "magnitude": empty, "signed_distance": empty}


def _surface_cascade(self, topology, graph, x_hat, free, a_start=None):
    """The garment stage against the inner layer's closest surface point at step t only, inner stages first."""
    pairs = graph.repulsion_pairs
    layer = topology.layer_index.to(pairs.device)
    a = torch.zeros_like(x_hat) if a_start is None else a_start
    stages = []
    for k in range(1, max(topology.num_layers, 2)):
        outer = pairs[0][layer[pairs[0]] == k]
        if len(outer) == 0 or len(topology.layer_surface(k - 1)[0]) == 0:
            continue
        x_k = x_hat + a
        n_k = vertex_normals(x_k, topology.faces)
        c_cur, c_next, n_c, keep = surface_partners(topology, graph.x_cur, x_k, n_k, outer, k - 1)
        outer, c_cur, c_next, n_c = outer[keep], c_cur[keep], c_next[keep], n_c[keep]
        a_k, ex = self.repulsion.push(outer, graph.x_cur[outer], x_k[outer], c_cur, c_next, n_c, x_hat.shape[0])
        a = a + a_k * free
        stages.append({"active_pairs": torch.stack([outer[ex["active"]], outer[ex["active"]]]),
                       "magnitude": ex["magnitude"], "signed_distance": ex["signed_distance"]})
    if not stages:
        return _off_cascade(self, topology, graph, x_hat, free, a_start)
    return a, {key: torch.cat([s[key] for s in stages], dim=-1) for key in stages[0]}


def _body_guarded(cascade):
    """Wrap a garment-stage cascade: the garment stages' push (not the body stage's) of each vertex with a body
    world edge keeps no component toward the body."""

    def guarded(self, topology, graph, x_hat, free, a_start=None):
        a, ex = cascade(topology, graph, x_hat, free, a_start)
        start = torch.zeros_like(a) if a_start is None else a_start
        a_layer = a - start
        q, f = graph.body_receivers, graph.body_features
        n_body = torch.zeros_like(a).index_copy(0, q, f[:, 9:12])
        inward = (a_layer * n_body).sum(-1, keepdim=True).clamp(max=0.0)
        return start + a_layer - inward * n_body, ex

    return guarded


def with_mode(model, mode: str):
    """A copy of ``model`` whose garment stage runs in ``mode`` (:data:`MODES`)."""
    m = copy.deepcopy(model)
    if mode == "off":
        m._cascade_repulsion = types.MethodType(_off_cascade, m)
    elif mode == "surface":
        m._cascade_repulsion = types.MethodType(_surface_cascade, m)
    elif mode == "deeper":
        m.config.repulsion_pairing = "deeper"
    elif mode in ("vertex", "nearest"):
        m.config.repulsion_pairing = mode
    elif mode.endswith("_body_guard"):
        m.config.repulsion_pairing = mode.removesuffix("_body_guard")
        m._cascade_repulsion = types.MethodType(_body_guarded(m._cascade_repulsion), m)
    else:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    return m


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="checkpoints/full")
    p.add_argument("--outfits", nargs="+", default=["tshirt_jacket"], help="split or names (smln eval's)")
    p.add_argument("--motions", nargs="+", default=["05_01_walk"])
    p.add_argument("--shape", default="female_average")
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    p.add_argument("--edge-length", type=float, default=0.035)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--body-pairing", choices=BODY_PAIRINGS,
                   help="read the body stage with this pairing in every mode (default: the checkpoint's)")
    p.add_argument("--json-dir", help="write <dir>/<mode>.json (smln eval --json form)")
    a = p.parse_args(argv)
    set_threads(a.threads)
    model, card = load_checkpoint(a.checkpoint)
    if not model.config.use_repulsion_layer:
        raise SystemExit(f"{a.checkpoint} has no repulsion layer")
    apply_body_pairing(model, a.body_pairing)
    outfits, motions = resolve_names(a.outfits, "outfits"), resolve_names(a.motions, "motions")
    out: dict[str, dict[str, float]] = {}
    for mode in a.modes:
        res = evaluate({mode: with_mode(model, mode)}, outfits, motions, shape=a.shape, frames=a.frames,
                       edge_length=a.edge_length, surface_metrics=True, progress=True)
        n = sum(r.metrics["num_frames"] for r in res)
        out[mode] = {k: sum(r.metrics[k] * r.metrics["num_frames"] for r in res) / n
                     for k in ("l_coll", "l_coll_surface", "h_coll", "h_coll_surface", "strain_mean")}
        out[mode]["fallback_frames"] = sum(r.metrics["fallback_frames"] for r in res)
        print(mode, json.dumps({k: round(v, 3) for k, v in out[mode].items()}), flush=True)
        if a.json_dir:
            Path(a.json_dir).mkdir(parents=True, exist_ok=True)
            rows = [{"method": r.method, "outfit": r.outfit, "motion": r.motion, "split": r.split,
                     "metrics": r.metrics} for r in res]
            Path(a.json_dir, f"{mode}.json").write_text(json.dumps(rows, indent=1))
    return out


if __name__ == "__main__":
    main()
