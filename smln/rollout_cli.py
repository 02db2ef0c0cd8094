"""``smln rollout``: animate an outfit on a clip with a checkpoint (or the reference solver) and save an NPZ."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from smln.body import BODY_SHAPES, DEFAULT_SHAPE
from smln.geometry import set_threads


def main(args: argparse.Namespace) -> None:
    run(args.argv)


def run(argv: list[str] | None = None) -> Path:
    from smln.data_sampling import make_scene
    from smln.evaluate import (
        add_model_rollout_options,
        apply_body_pairing,
        apply_repulsion_pairing,
        method_frames,
        rollout_guards,
    )
    from smln.export import save_rollout_npz

    p = argparse.ArgumentParser(prog="smln rollout", description=__doc__)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="checkpoint directory or .safetensors file")
    src.add_argument("--solver", action="store_true", help="the per-frame L-BFGS reference solver (no network)")
    src.add_argument("--skinning", action="store_true", help="garments rigidly skinned (no dynamics)")
    p.add_argument("--outfit", required=True)
    p.add_argument("--motion", required=True, help="clip name or path to a .bvh file")
    p.add_argument("--shape", default=DEFAULT_SHAPE, choices=list(BODY_SHAPES))
    p.add_argument("--frames", type=int)
    p.add_argument("--edge-length", type=float, default=0.02)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=2)
    add_model_rollout_options(p)
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    a = p.parse_args(argv)
    out = Path(a.out)
    if out.suffix != ".npz":  # numpy appends .npz: check (and report) the file that will really be written
        out = out.with_name(out.name + ".npz")
    if out.exists() and not a.force:
        raise FileExistsError(f"{out} exists; pass --force to overwrite it")
    set_threads(a.threads)
    model = None
    if a.checkpoint:
        from smln.checkpoint import load_checkpoint

        model, _ = load_checkpoint(a.checkpoint)
        apply_repulsion_pairing(model, a.repulsion_pairing)
        apply_body_pairing(model, a.body_pairing)
    kind = "model" if model is not None else ("solver" if a.solver else "skinning")
    scene = make_scene(a.outfit, a.shape, a.motion, edge_length=a.edge_length, max_frames=a.frames)
    t0 = time.time()
    if (a.project_body or a.project_layers) and kind != "model":
        raise ValueError("--project-body / --project-layers apply to a --checkpoint rollout")
    frames = list(method_frames(kind, model, scene, scene.num_frames, a.device, a.project_body, a.project_layers,
                                a.precision, a.compile, rollout_guards(a)))
    save_rollout_npz(out, frames, scene.cloth, scene.body.faces)
    fallback = sum(f.fallback for f in frames)
    print(f"wrote {out}: {len(frames)} frames, {scene.cloth.num_vertices} garment vertices, "
          f"{time.time() - t0:.1f} s" + (f", {fallback} frames fell back to skinning" if fallback else ""))
    return out
