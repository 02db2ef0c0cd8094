"""Does the skinned start cause the model's edge strain? The full model from skinning vs from rest with a lead-in.

The learned rollouts start from the garments skinned onto the clip's first frames (linear blend skinning of a
T-pose garment: 7-9 % mean edge strain). The physics reference starts from the rest garments in the T-pose and a
lead-in of the body to the clip's frame 1 (:func:`smln.motion.posing.preroll_sequence`). This script runs the full
model both ways on one outfit x clip and compares L-Coll, H-Coll and mean strain over the same clip frames
(``--skip`` onwards, in clip frame numbers).

    python bench/lead_in_start.py --outfit tshirt_jacket --clip 05_11_dance_sideways_steps_pirouette [--frames 141]
        [--lead-in 40] [--skip 10] [--checkpoint checkpoints/full]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from smln.body import load_body
from smln.checkpoint import load_checkpoint
from smln.data_sampling import make_scene
from smln.geometry import set_threads
from smln.motion.posing import preroll_sequence
from smln.rollout import rollout


def lead_in_sequence(body, sequence, lead_in: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(vertices (1 + lead_in + T - 2, Vb, 3), transforms) of: the rest pose, the lead-in to clip frame 1, clip
    frames 2 .. T-1. Clip frame k >= 1 is index k + lead_in - 1 of the result."""
    lead = preroll_sequence(body, sequence, frame=1, num_frames=lead_in)
    rest_transform = torch.zeros_like(sequence.transforms[:1])
    rest_transform[..., :3, :3] = torch.eye(3)
    verts = torch.cat([body.rest_vertices[None].float(), lead.vertices.float(), sequence.vertices[2:].float()])
    transforms = torch.cat([rest_transform.float(), lead.transforms.float(), sequence.transforms[2:].float()])
    return verts, transforms


def summary(frames, first: int) -> dict[str, float]:
    """Mean L-Coll / H-Coll / strain (%) and fallback count over frames with index >= first."""
    sel = [f for f in frames if f.index >= first]
    return {"l_coll": float(np.mean([f.metrics["l_coll"] for f in sel])),
            "h_coll": float(np.mean([f.metrics["h_coll"] for f in sel])),
            "strain_mean_pct": 100 * float(np.mean([f.metrics["strain_mean"] for f in sel])),
            "fallback_frames": int(sum(f.fallback for f in sel)), "frames": len(sel)}


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="checkpoints/full")
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--clip", default="05_11_dance_sideways_steps_pirouette")
    p.add_argument("--shape", default="female_average")
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--lead-in", type=int, default=40)
    p.add_argument("--skip", type=int, default=10, help="first clip frame in the statistics")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    set_threads(a.threads)
    model, _ = load_checkpoint(a.checkpoint)
    scene = make_scene(a.outfit, a.shape, a.clip, edge_length=0.035, max_frames=a.frames)
    skinned_start = list(rollout(model, scene.cloth, scene.body, scene.body.faces, fallback=True))
    seq = lead_in_sequence(load_body(a.shape), scene.body, a.lead_in)
    rest_start = list(rollout(model, scene.cloth, seq, scene.body.faces, fallback=True))
    out = {"skinned start": summary(skinned_start, a.skip),
           f"rest + {a.lead_in}-frame lead-in": summary(rest_start, a.skip + a.lead_in - 1)}
    print(f"{a.outfit} / {a.clip}, clip frames {a.skip}..{scene.num_frames - 1}:")
    for name, r in out.items():
        print(f"  {name:28s} L-Coll {r['l_coll']:.2f} %  H-Coll {r['h_coll']:.2f} %  "
              f"strain {r['strain_mean_pct']:.2f} %  fallback {r['fallback_frames']} of {r['frames']}")
    return out


if __name__ == "__main__":
    main()
