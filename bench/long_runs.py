"""Long runs: every shipped test clip x every outfit, full length, with a checkpoint (issue 9).

    nice -n 19 python bench/long_runs.py [--checkpoint checkpoints/full] [--outfits ...] [--clips ...]
                                         [--projection] [--precision bfloat16] [--json OUT.json] [--markdown OUT.md]

Each rollout runs with ``fallback=True`` (a diverged frame is replaced by skinning and flagged) and is summarised
as one row: frames, fallback frames, NaN frames, the largest distance of any garment vertex from the body
(nearest body vertex), the largest distance of a non-fallback frame from the skinned garment, mean and max
L-Coll / H-Coll (%), mean and max edge strain, and milliseconds per frame. ``check`` says whether the row meets
the reliability contract: no NaN, max distance from the body under :data:`MAX_BODY_DISTANCE`, every frame
either a network frame within the rollout's divergence bounds or a flagged fallback equal to skinning.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from smln.geometry import set_threads
from smln.rollout import MAX_BODY_DISTANCE as ROLLOUT_MAX_BODY_DISTANCE
from smln.rollout import MAX_SKIN_DISTANCE as ROLLOUT_MAX_SKIN_DISTANCE

MAX_BODY_DISTANCE = 0.5
"""Stated bound: no garment vertex farther than this from the nearest body vertex, m."""
MAX_SKIN_DISTANCE = ROLLOUT_MAX_SKIN_DISTANCE
"""The rollout's own divergence bound on the distance to skinning (``smln.rollout.rollout(max_distance=...)``), m.
The rollout also bounds the distance to the body (``max_body_distance``), below :data:`MAX_BODY_DISTANCE`."""
assert ROLLOUT_MAX_BODY_DISTANCE < MAX_BODY_DISTANCE  # the rollout's guard keeps the stated bound


@dataclass
class LongRunResult:
    """Summary of one full-length rollout (distances in m, collisions and strain in %)."""

    outfit: str
    clip: str
    frames: int
    vertices: int
    fallback_frames: int
    nan_frames: int
    max_body_distance: float
    max_skin_distance: float
    l_coll_mean: float
    l_coll_max: float
    h_coll_mean: float
    h_coll_max: float
    strain_mean: float
    strain_max: float
    ms_per_frame: float
    fallback_equals_skinning: bool

    @property
    def ok(self) -> bool:
        """The reliability contract of issue 9 holds for this run."""
        return (self.nan_frames == 0 and self.max_body_distance < MAX_BODY_DISTANCE
                and self.max_skin_distance <= MAX_SKIN_DISTANCE and self.fallback_equals_skinning)


def long_run(model: torch.nn.Module, outfit: str, clip: str, shape: str = "female_average",
             edge_length: float = 0.02, num_frames: int | None = None, device: str = "cpu", projection: bool = False,
             precision: str = "float32") -> LongRunResult:
    """Roll ``model`` out over ``clip`` (full length unless ``num_frames``) with ``outfit`` and summarise it
    (``projection``: with the body and layer collision projection; ``precision``: the processor's)."""
    from smln.data_sampling import make_scene
    from smln.rollout import rollout

    scene = make_scene(outfit, shape, clip, edge_length=edge_length)
    n = scene.num_frames if num_frames is None else min(num_frames, scene.num_frames)
    skinned = scene.skinned.numpy() if isinstance(scene.skinned, torch.Tensor) else np.asarray(scene.skinned)
    rows: list[dict[str, float]] = []
    fallback = nan = 0
    body_dist = skin_dist = 0.0
    fallback_ok = True
    t0 = time.perf_counter()
    for fr in rollout(model, scene.cloth, scene.body, scene.body.faces, num_frames=n, device=device, fallback=True,
                      project_body=projection, project_layers=projection, precision=precision):
        x = fr.garment_positions
        finite = bool(np.isfinite(x).all())
        nan += int(not finite)
        if finite:
            body_dist = max(body_dist, fr.metrics["body_distance_max"])  # nearest body vertex, the rollout's query
            d = float(np.linalg.norm(x - skinned[fr.index], axis=1).max())
            if fr.fallback:
                fallback_ok &= d < 1e-4
            else:
                skin_dist = max(skin_dist, d)
        fallback += int(fr.fallback)
        rows.append(dict(fr.metrics))
    seconds = time.perf_counter() - t0

    def stat(key: str, fn: np.ufunc) -> float:
        col = np.array([r.get(key, np.nan) for r in rows], dtype=np.float64)
        col = col[np.isfinite(col)]
        return float(fn(col)) if len(col) else float("nan")

    return LongRunResult(
        outfit=outfit, clip=clip, frames=len(rows), vertices=scene.cloth.num_vertices, fallback_frames=fallback,
        nan_frames=nan, max_body_distance=body_dist, max_skin_distance=skin_dist,
        l_coll_mean=stat("l_coll", np.mean), l_coll_max=stat("l_coll", np.max),
        h_coll_mean=stat("h_coll", np.mean), h_coll_max=stat("h_coll", np.max),
        strain_mean=100 * stat("strain_mean", np.mean), strain_max=100 * stat("strain_max", np.max),
        ms_per_frame=1000 * seconds / max(len(rows), 1), fallback_equals_skinning=fallback_ok,
    )


def markdown(results: list[LongRunResult], checkpoint: str) -> str:
    """The results as a markdown table."""
    lines = [
        f"Checkpoint `{checkpoint}`; body bound {MAX_BODY_DISTANCE} m. Distances in m; L-Coll, H-Coll, strain in %.",
        "",
        "| outfit | clip | frames | fallback | NaN | max dist body | max dist skin | L-Coll mean/max "
        "| H-Coll mean/max | strain mean/max | ms/frame | ok |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in results:
        lines.append(
            f"| {r.outfit} | {r.clip} | {r.frames} | {r.fallback_frames} | {r.nan_frames} | "
            f"{r.max_body_distance:.3f} | {r.max_skin_distance:.3f} | {r.l_coll_mean:.1f} / {r.l_coll_max:.1f} | "
            f"{r.h_coll_mean:.1f} / {r.h_coll_max:.1f} | {r.strain_mean:.1f} / {r.strain_max:.0f} | "
            f"{r.ms_per_frame:.0f} | {'yes' if r.ok else 'NO'} |")
    total = sum(r.frames for r in results)
    fb = sum(r.fallback_frames for r in results)
    lines += ["", f"{len(results)} runs, {total} frames, {fb} fallback frames "
              f"({100 * fb / max(total, 1):.1f} %), {sum(not r.ok for r in results)} runs failing the contract."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[LongRunResult]:
    from smln.checkpoint import load_checkpoint
    from smln.garments import OUTFITS
    from smln.motion import list_clips

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="checkpoints/full")
    p.add_argument("--outfits", nargs="+", default=list(OUTFITS))
    p.add_argument("--clips", nargs="+", default=list_clips("test"))
    p.add_argument("--shape", default="female_average")
    p.add_argument("--edge-length", type=float, default=0.02)
    p.add_argument("--frames", type=int, help="frames per clip (default: the whole clip)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu")
    p.add_argument("--projection", action="store_true", help="with the body and layer collision projection")
    p.add_argument("--precision", default="float32", choices=["float32", "bfloat16"])
    p.add_argument("--json", help="write the rows as JSON")
    p.add_argument("--markdown", help="write the table as markdown")
    a = p.parse_args(argv)
    set_threads(a.threads)
    model, _ = load_checkpoint(a.checkpoint, map_location=a.device)
    results = []
    for clip in a.clips:
        for outfit in a.outfits:
            r = long_run(model, outfit, clip, a.shape, a.edge_length, a.frames, a.device, a.projection, a.precision)
            results.append(r)
            print(f"{outfit:26s} {clip:40s} {r.frames:4d} frames, {r.fallback_frames:3d} fallback, "
                  f"body {r.max_body_distance:.3f} m, L-Coll {r.l_coll_mean:5.1f} %, "
                  f"{r.ms_per_frame:.0f} ms/frame {'ok' if r.ok else 'FAIL'}", flush=True)
            if a.json:  # written as it goes: a long run can be stopped and still leaves its rows
                Path(a.json).write_text(json.dumps([asdict(x) | {"ok": x.ok} for x in results], indent=1))
    table = markdown(results, a.checkpoint)
    print(table)
    if a.markdown:
        Path(a.markdown).write_text(table + "\n")
    return results


if __name__ == "__main__":
    main()
