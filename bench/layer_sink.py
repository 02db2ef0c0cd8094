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

Several scenes at once (session 41): ``--outfit`` and ``--motion`` take several names or a split (``--motion test``;
outfits with one layer are skipped: they have no layer to rest on). Each scene prints its table, then a summary at
frame ``--at`` (default 50; scenes shorter than that are left out): per checkpoint the mean sink over the scenes, and
for every checkpoint after the first its paired difference from the first (mean ± standard error over the scenes, and
on how many it sinks less / more), so that one clip's measurement is not read alone.
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


def measure(checkpoint: str, model, scene, frames: int, band: np.ndarray) -> dict:
    """Roll the loaded checkpoint (``model``, read from the path ``checkpoint``) out (the shipped guards, fallback to
    skinning) and measure the band's sink and the slip."""
    out = list(rollout(model, scene.cloth, scene.body, scene.body.faces, num_frames=frames, fallback=True))
    x = np.stack([f.garment_positions for f in out])
    sink = band_sink(x, scene.skinned[:frames].numpy(), band)
    slips = [layer_slip(x[t - 1], x[t], scene.rest) for t in range(1, frames)
             if not (out[t].fallback or out[t - 1].fallback)]  # a reset to skinning is no slip
    return {"checkpoint": checkpoint, "sink_mm": sink.tolist(), "fallback_frames": int(sum(f.fallback for f in out)),
            "layer_slip_mm": 1e3 * float(np.nanmean(slips))}


def paired_summary(sinks: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """Mean sink per label and each label's paired difference from the first label, over the same scenes.

    Args:
        sinks: label -> the sink of each scene at one frame, mm (the same scenes, in the same order, for every label).

    Returns:
        label -> ``{"mean_mm", "scenes"}`` plus, for labels after the first, ``"diff_mm"`` (mean of the per-scene
        differences, label minus first), ``"diff_se_mm"`` (its standard error; nan with one scene), ``"less"`` and
        ``"more"`` (scenes where the label sinks less / more than the first).
    """
    labels = list(sinks)
    ref = np.asarray(sinks[labels[0]], dtype=float)
    out: dict[str, dict[str, float]] = {}
    for label in labels:
        v = np.asarray(sinks[label], dtype=float)
        if v.shape != ref.shape:
            raise ValueError(f"{label!r} has {v.size} scenes, {labels[0]!r} {ref.size}")
        row = {"mean_mm": float(v.mean()) if v.size else float("nan"), "scenes": int(v.size)}
        if label != labels[0]:
            d = v - ref
            row["diff_mm"] = float(d.mean()) if d.size else float("nan")
            row["diff_se_mm"] = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("nan")
            row["less"], row["more"] = int((d < 0).sum()), int((d > 0).sum())
        out[label] = row
    return out


def measure_scene(outfit: str, motion: str, checkpoints: list[str], frames: int, band_m: float,
                  report: list[int], models: dict) -> dict:
    """Every checkpoint on one scene: prints its table and returns the scene's result (JSON form). ``models``: the
    checkpoints loaded once for all scenes, by path."""
    scene = make_scene(outfit, "female_average", motion, edge_length=0.035, max_frames=frames)
    frames = min(frames, scene.body.num_frames)
    band = top_band(scene.skinned[0].numpy(), scene.cloth.layer_index.numpy(), band_m)
    report = [t for t in report if t < frames]
    result: dict = {"outfit": outfit, "motion": motion, "frames": frames, "band_m": band_m,
                    "band_vertices": int(band.size), "runs": {}}
    print(f"{outfit} on {motion}: top {band_m * 100:.0f} cm of the outer layer ({band.size} vertices), "
          f"mm below the skinned place")
    print("label".ljust(24) + "".join(f"f{t}".rjust(8) for t in report) + "   slip mm/frame  fallbacks")
    for spec in checkpoints:
        label, _, path = spec.rpartition("=")
        run = measure(path, models[path], scene, frames, band)
        result["runs"][label or path] = run
        print((label or path)[:23].ljust(24) + "".join(f"{run['sink_mm'][t]:8.0f}" for t in report)
              + f"   {run['layer_slip_mm']:13.2f}  {run['fallback_frames']:9d}", flush=True)
    return result


def main(argv: list[str] | None = None) -> dict:
    from smln.evaluate import resolve_names
    from smln.garments import outfit_registry

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoints", nargs="+", default=["shipped=checkpoints/full"], metavar="LABEL=PATH")
    p.add_argument("--outfit", "--outfits", dest="outfits", nargs="+", default=["tshirt_jacket"],
                   help="outfit names or a split")
    p.add_argument("--motion", "--motions", dest="motions", nargs="+", default=["05_01_walk"],
                   help="clip names or a split")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--band", type=float, default=0.12, help="height of the top band, meters")
    p.add_argument("--report", type=int, nargs="+", default=[10, 30, 50, 70, 90], help="frames to print")
    p.add_argument("--at", type=int, default=50, help="several scenes: the frame of the summary")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json")
    args = p.parse_args(argv)
    set_threads(args.threads)
    registry = outfit_registry()
    outfits = [o for o in resolve_names(args.outfits, "outfits") if len(registry.get(o, {}).get("layers", [])) > 1]
    motions = resolve_names(args.motions, "motions")
    if not outfits:
        raise SystemExit("no outfit with two or more layers among " + " ".join(args.outfits))
    models = {path: load_checkpoint(path)[0] for path in (spec.rpartition("=")[2] for spec in args.checkpoints)}
    scenes = [measure_scene(o, m, args.checkpoints, args.frames, args.band, args.report, models)
              for o in outfits for m in motions]
    if len(scenes) == 1:
        result = scenes[0]
    else:
        long_enough = [sc for sc in scenes if sc["frames"] > args.at]
        labels = list(scenes[0]["runs"])
        summary = paired_summary({lb: [sc["runs"][lb]["sink_mm"][args.at] for sc in long_enough] for lb in labels})
        print(f"summary at frame {args.at} over {len(long_enough)} of {len(scenes)} scenes (mm below skinning)")
        for lb, row in summary.items():
            extra = (f"   {lb} - {labels[0]}: {row['diff_mm']:+.1f} ± {row['diff_se_mm']:.1f} (SE), less on "
                     f"{row['less']}, more on {row['more']}") if "diff_mm" in row else ""
            print(f"{lb[:23].ljust(24)}{row['mean_mm']:8.1f}{extra}")
        result = {"scenes": scenes, "summary_frame": args.at, "summary": summary}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
