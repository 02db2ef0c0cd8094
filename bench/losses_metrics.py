"""Benchmark: metrics of one frame and one total_loss forward+backward on a 2-layer ~5k-vertex outfit.

Setup: a body-like mesh of 12,804 vertices (an ellipsoid torso, icosphere subdivision 5, plus a head,
subdivision 4) and two open elliptical tubes of 50 x 50 vertices each that follow the torso 1 cm and 2 cm
outside it (5,000 cloth vertices, 9,800 faces). Reports medians of 20 runs (after 3 warm-ups) with
``torch.set_num_threads(2)``, as JSON. The :func:`frame_metrics` variants run interleaved (round robin), so a
busy machine slows them alike and their ratios stay comparable:

- ``metrics_ms``: self-contained, as the evaluation scripts call it (``body_faces`` only): the body KD-tree
  (build + query of the 5,000 cloth vertices) and the normals of the body vertices it needs are computed
  inside; one thread.
- ``metrics_shared_tree_ms``: the body tree given, normals from the faces: what :func:`smln.rollout.rollout`
  pays per frame (it builds one tree per body frame and shares it with the graph build of the next step).
- ``metrics_prebuilt_body_ms``: body normals and tree both given.
- ``*_2workers_ms``: the same with ``workers=2`` (the KD-tree queries split over two threads; the tree build
  and the numpy work stay on one).
- ``loss_fwd_bwd_ms``: :func:`total_loss` forward + backward with a prebuilt :class:`BodyStep`
  (``_incl_body_step``: building it too; ``_cached_pairs``: with the repulsion pairs given).

Target (issue 4): ``metrics_ms`` <= 5 ms median on 2 idle CPU cores; it measured 10.5-11.3 ms before the
numpy/scipy rewrite of :func:`frame_metrics` (torch vertex normals and index_add, row gathers). What is left is
mostly scipy's cKDTree: building the 12.8k-vertex body tree, querying the 5,000 cloth vertices in it and the
2,500-point layer query take about 80 % of a single-threaded call. Interleaved A/B runs against the previous
version on a loaded 2-core machine, one thread, as fractions of the previous self-contained time: self-contained
0.75, body tree shared 0.63, body tree and normals given 0.56 (the previous version with both given: 0.71).
With ``workers=2`` the queries (~60 % of the CPU time) split over the two cores: from the per-thread CPU times,
on 2 idle cores about 0.57-0.61 self-contained, 0.44-0.47 with the tree shared, 0.39-0.41 with both given
(estimates: on the loaded machine two threads ran no faster than one). So 5 ms is within reach only with the
body tree shared and ``workers=2`` (the rollout shares the tree but calls with the default ``workers=1``); check
it on an idle machine with this script.

Run: ``python bench/losses_metrics.py``
"""

from __future__ import annotations

import json
import platform
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch
import trimesh

from smln.cloth import Cloth, Material
from smln.geometry import build_tree, vertex_normals
from smln.losses import BodyStep, ClothRest, layer_pairs, total_loss
from smln.metrics import frame_metrics

AXES = np.array([0.18, 0.13, 0.45])  # torso ellipsoid semi-axes, m
CENTER = np.array([0.0, 0.0, 1.2])


def make_body() -> tuple[np.ndarray, np.ndarray]:
    """(Vb, 3), (Fb, 3): ellipsoid torso + spherical head, ~12.8k vertices, roughly uniform spacing."""
    torso = trimesh.creation.icosphere(subdivisions=5)
    torso.vertices = torso.vertices * AXES + CENTER
    head = trimesh.creation.icosphere(subdivisions=4, radius=0.11)
    head.vertices = head.vertices + CENTER + [0, 0, AXES[2] + 0.13]
    body = trimesh.util.concatenate([torso, head])
    return np.asarray(body.vertices, np.float32), np.asarray(body.faces, np.int64)


def make_tube(offset: float, n_theta: int = 50, n_z: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """An open elliptical tube around the torso between z = c +- 0.3 m, ``offset`` m outside it."""
    th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    z = np.linspace(-0.3, 0.3, n_z)
    tt, zz = np.meshgrid(th, z, indexing="ij")
    s = np.sqrt(1 - (zz / AXES[2]) ** 2)
    v = np.stack(
        [(AXES[0] * s + offset) * np.cos(tt), (AXES[1] * s + offset) * np.sin(tt), zz + CENTER[2]], -1
    ).reshape(-1, 3)
    i = np.arange(n_theta * n_z).reshape(n_theta, n_z)
    j = np.roll(i, -1, axis=0)
    a, b, c, d = i[:, :-1].ravel(), j[:, :-1].ravel(), j[:, 1:].ravel(), i[:, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v.astype(np.float32), f


def make_cloth() -> Cloth:
    layers = [make_tube(0.01), make_tube(0.02)]
    m = Material()
    x = torch.as_tensor(np.concatenate([v for v, _ in layers]))
    f = torch.as_tensor(np.concatenate([layers[0][1], layers[1][1] + len(layers[0][0])]))
    area = 0.5 * torch.linalg.norm(torch.linalg.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]]), dim=-1)
    mass = torch.zeros(len(x)).index_add(0, f.reshape(-1), (m.density * area / 3).repeat_interleave(3))
    n = len(x)
    pinned = torch.zeros(n, dtype=torch.bool)
    pinned[x[:, 2] > x[:, 2].max() - 1e-4] = True  # top rings
    return Cloth(
        rest_vertices=x,
        faces=f,
        layer_index=torch.as_tensor(np.repeat([0, 1], [len(v) for v, _ in layers])),
        vertex_mass=mass,
        pinned=pinned,
        skin_indices=torch.zeros(n, 1, dtype=torch.long),
        skin_weights=torch.ones(n, 1),
        material=m,
    )


def interleaved_median_ms(fns: dict[str, Callable[[], object]], runs: int = 20, warmup: int = 3) -> dict[str, float]:
    """Median ms of each function, running them round robin (each round calls every function once)."""
    ts: dict[str, list[float]] = {k: [] for k in fns}
    for r in range(warmup + runs):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            if r >= warmup:
                ts[k].append(time.perf_counter() - t)
    return {k: 1e3 * statistics.median(v) for k, v in ts.items()}


def median_ms(fn: Callable[[], object], runs: int = 20, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1e3 * statistics.median(ts)


def main() -> None:
    torch.set_num_threads(2)
    torch.manual_seed(0)
    bv, bf = make_body()
    body = torch.as_tensor(bv)
    body_faces = torch.as_tensor(bf)
    body_next = body + torch.tensor([0.003, 0.0, 0.001])
    cloth = make_cloth()
    rest = ClothRest.from_cloth(cloth)
    x_prev = cloth.rest_vertices.clone()
    x_cur = x_prev + 0.001
    x_next0 = x_cur + 0.001 + 0.0005 * torch.randn_like(x_cur)
    x_next0[cloth.pinned] = x_cur[cloth.pinned]
    x_np = x_next0.numpy()
    bn = vertex_normals(body_next, body_faces)
    tree = build_tree(body_next)
    step = BodyStep.from_vertices(body, body_next, body_faces)
    pairs = layer_pairs(x_cur, rest)

    def loss_fb(step: BodyStep = step, pairs: torch.Tensor | None = None) -> None:
        x = x_next0.clone().requires_grad_(True)
        loss, _ = total_loss(x_prev, x_cur, x, step, rest, pairs=pairs)
        loss.backward()

    m = frame_metrics(x_np, body_next, rest, body_faces=body_faces)
    metrics = interleaved_median_ms(
        {
            f"metrics{name}{'_2workers' if w == 2 else ''}_ms": (
                lambda kw=kw, w=w: frame_metrics(x_np, body_next, rest, workers=w, **kw)
            )
            for name, kw in (
                ("", {"body_faces": body_faces}),
                ("_shared_tree", {"body_faces": body_faces, "body_tree": tree}),
                ("_prebuilt_body", {"body_normals": bn, "body_tree": tree}),
            )
            for w in (1, 2)
        }
    )
    result = {
        "body_vertices": int(body.shape[0]),
        "cloth_vertices": int(cloth.num_vertices),
        "cloth_faces": int(cloth.faces.shape[0]),
        "layer_pairs": int(pairs.shape[0]),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "threads": torch.get_num_threads(),
        "runs": 20,
        **metrics,
        "body_step_build_ms": median_ms(lambda: BodyStep.from_vertices(body, body_next, body_faces)),
        "loss_fwd_bwd_ms": median_ms(loss_fb),
        "loss_fwd_bwd_cached_pairs_ms": median_ms(lambda: loss_fb(pairs=pairs)),
        "loss_fwd_bwd_incl_body_step_ms": median_ms(
            lambda: loss_fb(step=BodyStep.from_vertices(body, body_next, body_faces))
        ),
        "sample_metrics": {k: round(v, 6) for k, v in m.values.items()},
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
