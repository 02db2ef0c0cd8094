"""Benchmark: does the outer garment stay on the layer beneath? The sink of its top band over a clip.

An open jacket over a t-shirt rests on the t-shirt's shoulders. If the learned friction between the layers is too
weak it slides down over a walk (docs/RESULTS.md, session 11: the shipped model's jacket top sat 94 mm below its
skinned place by frame 50 of 05_01_walk, the Newton physics reference's 52 mm). No target metric sees this, so
this script measures it: the outermost layer's *top band* (its vertices within ``--band`` of the layer's highest
vertex in the clip's first skinned frame: the shoulders and collar, arms down) and, per frame, how far the band's
mean height lies below the same vertices skinned onto the body (mm; 0 for skinning by construction, positive =
sunk). Also printed: the mean
tangential slip of touching layer pairs (:func:`smln.metrics.layer_slip`, mm/frame) over the clip (frames at and
after a fallback to skinning left out, as in ``smln eval``).

Run: ``python bench/layer_sink.py --checkpoints shipped=checkpoints/full [other=PATH ...] [--outfit tshirt_jacket]
[--motion 05_01_walk] [--frames 100] [--report 10 30 50 70 90] [--json OUT]`` (about 20 s per checkpoint and 100
frames on one core).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from smln.checkpoint import load_checkpoint
from smln.data_sampling import make_scene
from smln.geometry import set_threads
from smln.metrics import layer_slip
from smln.rollout import rollout


def top_band(vertices: np.ndarray, layer_index: np.ndarray, band: float) -> np.ndarray:
    """Indices of the outermost layer's vertices within ``band`` m (Z up) of that layer's highest vertex.

    Args:
        vertices: (V, 3) garment positions (here the first skinned frame), meters; layer_index: (V,) int, 0 =
            innermost.
    Returns:
        (K,) int64 vertex indices.
    """
    outer = np.flatnonzero(layer_index == layer_index.max())
    z = vertices[outer, 2]
    return outer[z >= z.max() - band]


def band_sink(positions: np.ndarray, skinned: np.ndarray, band: np.ndarray) -> np.ndarray:
    """(T,) mean height of the band's vertices below their skinned place, mm (positive = below).

    Args:
        positions, skinned: (T, V, 3) garment vertices of the method and of skinning, meters.
    """
    return 1e3 * (skinned[:, band, 2] - positions[:, band, 2]).mean(axis=1)


def measure(checkpoint: str, scene, frames: int, band: np.ndarray) -> dict:
    """Roll the checkpoint out (the shipped guards, fallback to skinning) and measure the band's sink and the slip."""
    model, _ = load_checkpoint(checkpoint)
    out = list(rollout(model, scene.cloth, scene.body, scene.body.faces, num_frames=frames, fallback=True))
    x = np.stack([f.garment_positions for f in out])
    sink = band_sink(x, scene.skinned[:frames].numpy(), band)
    slips = [layer_slip(x[t - 1], x[t], scene.rest) for t in range(1, frames)
             if not (out[t].fallback or out[t - 1].fallback)]  # a reset to skinning is no slip
    return {"checkpoint": checkpoint, "sink_mm": sink.tolist(), "fallback_frames": int(sum(f.fallback for f in out)),
            "layer_slip_mm": 1e3 * float(np.nanmean(slips))}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoints", nargs="+", default=["shipped=checkpoints/full"], metavar="LABEL=PATH")
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--motion", default="05_01_walk")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--band", type=float, default=0.12, help="height of the top band, meters")
    p.add_argument("--report", type=int, nargs="+", default=[10, 30, 50, 70, 90], help="frames to print")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json")
    args = p.parse_args(argv)
    set_threads(args.threads)
    scene = make_scene(args.outfit, "female_average", args.motion, edge_length=0.035, max_frames=args.frames)
    frames = min(args.frames, scene.body.num_frames)
    band = top_band(scene.skinned[0].numpy(), scene.cloth.layer_index.numpy(), args.band)
    report = [t for t in args.report if t < frames]
    result: dict = {"outfit": args.outfit, "motion": args.motion, "frames": frames, "band_m": args.band,
                    "band_vertices": int(band.size), "runs": {}}
    print(f"{args.outfit} on {args.motion}: top {args.band * 100:.0f} cm of the outer layer ({band.size} vertices), "
          f"mm below the skinned place")
    print("label".ljust(24) + "".join(f"f{t}".rjust(8) for t in report) + "   slip mm/frame  fallbacks")
    for spec in args.checkpoints:
        label, _, path = spec.rpartition("=")
        run = measure(path, scene, frames, band)
        result["runs"][label or path] = run
        print((label or path)[:23].ljust(24) + "".join(f"{run['sink_mm'][t]:8.0f}" for t in report)
              + f"   {run['layer_slip_mm']:13.2f}  {run['fallback_frames']:9d}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
