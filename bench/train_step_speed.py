"""Benchmark: time per training step (forward, losses, backward, Adam, EMA), eager vs ``--compile``.

Runs ``Trainer.train_step`` on one scene (outfit, body ``female_average``, clip), ``--steps`` steps per repetition,
alternating eager and compiled repetitions so that both see the same machine load, and reports the median
ms/step of each and their ratio. The compiled processor is built once before timing (its one-off compilation time
is reported separately). Weights: the shipped checkpoint's (``--checkpoint``), so the graph and loss terms are
those of a trained model.

Run: ``python bench/train_step_speed.py [--outfit tshirt_jacket] [--motion 02_01_walk] [--steps 20] [--reps 3]
[--threads 1] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from smln.checkpoint import load_checkpoint
from smln.geometry import set_threads
from smln.model.compiled import with_compiled_processor
from smln.train import TrainConfig, Trainer


def _time_steps(trainer: Trainer, net: torch.nn.Module, scene, steps: int, start: int = 20) -> float:
    """ms per training step over ``steps`` autoregressive steps from the skinned state at ``start``."""
    trainer.net = net
    x_prev, x_cur = scene.skinned[start - 1].clone(), scene.skinned[start].clone()
    t0 = time.perf_counter()
    for k in range(steps):
        x_next, _ = trainer.train_step(scene, start + k, x_prev, x_cur)
        x_prev, x_cur = x_cur, x_next
    return 1e3 * (time.perf_counter() - t0) / steps


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="checkpoints/full")
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--motion", default="02_01_walk")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json")
    args = p.parse_args(argv)
    set_threads(args.threads)
    model, _ = load_checkpoint(args.checkpoint)
    cfg = TrainConfig(outfits=[args.outfit], motions=[args.motion], shapes=["female_average"],
                      model=model.config.to_dict())
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(cfg, Path(tmp))
    trainer.model.load_state_dict(model.state_dict())
    scene = trainer.cache.get(args.outfit, "female_average", args.motion)
    eager = trainer.model
    compiled = with_compiled_processor(trainer.model, training=True)
    t0 = time.perf_counter()
    _time_steps(trainer, compiled, scene, 2)
    compile_s = time.perf_counter() - t0
    eager_ms, compiled_ms = [], []
    for _ in range(args.reps):
        eager_ms.append(_time_steps(trainer, eager, scene, args.steps))
        compiled_ms.append(_time_steps(trainer, compiled, scene, args.steps))
    out = {
        "outfit": args.outfit, "motion": args.motion, "vertices": scene.cloth.num_vertices, "threads": args.threads,
        "steps": args.steps, "reps": args.reps, "compile_s": round(compile_s, 1),
        "eager_ms_median": float(np.median(eager_ms)), "compiled_ms_median": float(np.median(compiled_ms)),
        "eager_ms": eager_ms, "compiled_ms": compiled_ms,
        "compile_failed": compiled.processor.failed, "torch": torch.__version__, "machine": platform.processor(),
    }
    out["ratio_compiled_over_eager"] = out["compiled_ms_median"] / out["eager_ms_median"]
    print(f"{args.outfit} / {args.motion} ({out['vertices']} vertices, {args.threads} thread(s)): eager "
          f"{out['eager_ms_median']:.1f} ms/step, compiled {out['compiled_ms_median']:.1f} ms/step "
          f"(ratio {out['ratio_compiled_over_eager']:.2f}; compilation {compile_s:.0f} s)")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
