"""Benchmark: metrics of one frame and one total_loss forward+backward on a 2-layer ~5k-vertex outfit.

Setup: a body-like mesh of 12,804 vertices (an ellipsoid torso, icosphere subdivision 5, plus a head,
subdivision 4) and two open elliptical tubes of 50 x 50 vertices each that follow the torso 1 cm and 2 cm
outside it (5,000 cloth vertices, 9,800 faces). Reports medians of 20 runs (after 3 warm-ups) with
2 threads (``--threads``), as JSON. The :func:`frame_metrics` variants run interleaved (round robin), so a
busy machine slows them alike and their ratios stay comparable:

- ``metrics_ms``: self-contained, as the evaluation scripts call it (``body_faces`` only): the body KD-tree
  (build + query of the 5,000 cloth vertices) and the normals of the body vertices it needs are computed
  inside.
- ``metrics_shared_tree_ms``: the body tree given, normals from the faces: what :func:`smln.rollout.rollout`
  pays per frame (it builds one tree per body frame and shares it with the graph build of the next step).
- ``metrics_prebuilt_body_ms``: body normals and tree both given.
- ``loss_fwd_bwd_ms``: :func:`total_loss` forward + backward with a prebuilt :class:`BodyStep`
  (``_incl_body_step``: building it too; ``_cached_pairs``: with the repulsion pairs given).

- ``real_*``: the same calls on the real scene of the issue: the 2-layer tshirt_jacket at 2 cm edges (4,976
  vertices) skinned onto the 12,272-vertex ``female_average`` body at frame 20 of the walk 02_01 (``--no-real`` skips
  it).

``--threads N`` (default 2) sets torch's threads and the KD-tree queries' OpenMP threads
(:func:`smln.geometry.set_threads`).

Targets (issue 4): ``metrics_ms`` <= 5 ms and ``loss_fwd_bwd_ms`` <= 20 ms, medians on 2 idle CPU cores. History
on this machine (idle): session 2 metrics 15.6 ms (numpy/scipy rewrite), session 3 10.1 ms self-contained and
loss 22.6-24.6 ms; session 4 replaced scipy's cKDTree by pykdtree (float32, OpenMP queries) and rewrote the
losses coordinate-major (see docs/RESULTS.md for the figures).

Run: ``python bench/losses_metrics.py``
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import trimesh

from smln.cloth import Cloth, Material
from smln.geometry import build_tree, set_threads, vertex_normals
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


def real_scene_ms(frame: int = 20) -> dict[str, float]:
    """Metrics (self-contained) and loss forward + backward on tshirt_jacket@2 cm on the real body (see above)."""
    from smln.data_sampling import make_scene

    scene = make_scene("tshirt_jacket", "female_average", "02_01_walk", edge_length=0.02, max_frames=frame + 2)
    faces = torch.as_tensor(scene.body.faces)
    body_cur, body_next = scene.body.vertices[frame], scene.body.vertices[frame + 1]
    x_prev, x_cur = scene.skinned[frame - 1], scene.skinned[frame]
    gen = torch.Generator().manual_seed(0)
    x_next = scene.skinned[frame + 1] + 0.0005 * torch.randn(x_cur.shape, generator=gen)
    x_np = x_next.numpy()
    step = BodyStep.from_vertices(body_cur, body_next, faces)

    def loss_fb() -> None:
        x = x_next.clone().requires_grad_(True)
        loss, _ = total_loss(x_prev, x_cur, x, step, scene.rest)
        loss.backward()

    return {
        "real_scene": f"tshirt_jacket@0.02 ({scene.cloth.num_vertices} vertices) on female_average "
                      f"({body_next.shape[0]} vertices), 02_01_walk frame {frame}",
        "real_metrics_ms": median_ms(lambda: frame_metrics(x_np, body_next, scene.rest, body_faces=faces)),
        "real_loss_fwd_bwd_ms": median_ms(loss_fb),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2, help="torch and KD-tree threads")
    ap.add_argument("--json", help="write the results here too")
    ap.add_argument("--no-real", dest="real", action="store_false", help="skip the real outfit-on-body rows")
    args = ap.parse_args()
    set_threads(args.threads)
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
            f"metrics{name}_ms": (lambda kw=kw: frame_metrics(x_np, body_next, rest, **kw))
            for name, kw in (
                ("", {"body_faces": body_faces}),
                ("_shared_tree", {"body_faces": body_faces, "body_tree": tree}),
                ("_prebuilt_body", {"body_normals": bn, "body_tree": tree}),
            )
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
    if args.real:
        result.update(real_scene_ms())
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
