"""Benchmark: does a rollout's body penetration follow the body's speed?

Rolls a checkpoint out on outfit x clip scenes and relates each frame's H-Coll (%, the metric of ``smln eval``) to
the body's mean vertex speed over the frames before it (m/frame, a moving window). A high correlation says the
model's body penetrations are where the motion is fast (jumps, landings, pirouettes), the motivation of
``smln train --start-sampling speed`` (session 21): with uniform start frames those phases are rare in training.
Frames that fell back to skinning keep their (skinned) H-Coll: they are part of what the evaluation counts.
The rigidly skinned garment gets the same figures: where its H-Coll follows the speed too, the fast phases are
poses that are hard for any garment (the body's own self-intersections), not only steps the network gets wrong.

Run: ``python bench/hcoll_speed.py --checkpoint checkpoints/full --scenes tshirt_jacket:01_14_climb_jump_down
leggings_skirt:05_11_dance_sideways_steps_pirouette [--frames 300] [--window 10] [--json OUT]``
(about 1 minute per 150 frames on one core).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from smln.body import DEFAULT_SHAPE
from smln.checkpoint import load_checkpoint
from smln.data_sampling import make_scene
from smln.evaluate import skinning_frames
from smln.geometry import set_threads
from smln.motion.posing import body_speed
from smln.rollout import rollout


def trailing_mean(x: np.ndarray, window: int) -> np.ndarray:
    """(T,) mean of x over frames t-window+1 .. t (fewer at the start)."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    t = np.arange(1, x.shape[0] + 1)
    lo = np.maximum(t - window, 0)
    return (c[t] - c[lo]) / (t - lo)


def speed_correlation(h_coll: np.ndarray, speed: np.ndarray, window: int) -> float:
    """Pearson correlation of per-frame H-Coll with the trailing ``window``-frame mean body speed, frames
    ``window`` onwards (the first ones mix in the skinned start). NaN if either is constant there."""
    s = trailing_mean(speed, window)[window:]
    h = h_coll[window:]
    if h.size < 3 or h.std() == 0 or s.std() == 0:
        return float("nan")
    return float(np.corrcoef(s, h)[0, 1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="checkpoints/full")
    p.add_argument("--scenes", nargs="+", default=["tshirt_jacket:01_14_climb_jump_down",
                                                   "leggings_skirt:05_11_dance_sideways_steps_pirouette"],
                   help="OUTFIT:CLIP ...")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--window", type=int, default=10, help="frames of the trailing body-speed mean")
    p.add_argument("--edge-length", type=float, default=0.035)
    p.add_argument("--json", type=Path)
    a = p.parse_args()
    set_threads(1)
    torch.set_num_threads(1)
    model, _ = load_checkpoint(a.checkpoint)
    report = {}
    for spec in a.scenes:
        outfit, _, motion = spec.partition(":")
        scene = make_scene(outfit, DEFAULT_SHAPE, motion, edge_length=a.edge_length, max_frames=a.frames)
        frames = list(rollout(model, scene.cloth, scene.body, scene.body.faces, num_frames=scene.num_frames,
                              fallback=True))
        h = np.array([f.metrics["h_coll"] for f in frames])
        h_skin = np.array([f.metrics["h_coll"] for f in skinning_frames(scene, len(h))])
        speed = body_speed(scene.body.vertices[: len(h)])
        recent = trailing_mean(speed, a.window)
        fast = recent > np.median(recent)
        report[spec] = {
            "frames": len(h),
            "fallback_frames": int(sum(f.fallback for f in frames)),
            "per_frame_speed": speed.round(6).tolist(),
        }
        for label, hc in (("model", h), ("skinning", h_skin)):
            r = {
                "h_coll": float(hc.mean()),
                "correlation": speed_correlation(hc, speed, a.window),
                "h_coll_fast_half": float(hc[fast].mean()),
                "h_coll_slow_half": float(hc[~fast].mean()),
                "per_frame_h_coll": hc.round(4).tolist(),
            }
            report[spec][label] = r
            print(f"{spec} {label:8s}: {len(h)} frames, H-Coll {r['h_coll']:.2f} % (faster half of the frames "
                  f"{r['h_coll_fast_half']:.2f} %, slower half {r['h_coll_slow_half']:.2f} %), correlation with the "
                  f"{a.window}-frame body speed {r['correlation']:.2f}"
                  + (f", {report[spec]['fallback_frames']} fallback frames" if label == "model" else ""))
    if a.json:
        a.json.write_text(json.dumps({"checkpoint": a.checkpoint, "window": a.window, "scenes": report}, indent=1))


if __name__ == "__main__":
    main()
