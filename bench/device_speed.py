"""Speed of the shipped model's rollout and of training steps on one device (CPU or GPU), for the GPU machine.

- inference: median ms/frame of :func:`smln.rollout.rollout` frames (graph build, network, repulsion layer,
  per-frame metrics; each frame ends with its positions on the host, so the timing includes the GPU's work) of
  the shipped full checkpoint on ``tshirt_jacket`` at 2 cm on ``02_01_walk``;
- training: steps/s of :class:`smln.train.Trainer` episodes with the shipped run's recipe
  (``docs/results/r27_config.json``: 3.5 cm training outfits, rollouts growing to 96 steps), after one warm-up
  episode, over ``--train-seconds``.

    python bench/device_speed.py --device cuda [--json OUT] [--frames 60] [--train-seconds 60]

Prints JSON (and writes it with ``--json``); run it with ``--device cpu`` beside for the ratio. On the CPU use
``--threads`` (default 2).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]


def inference(device: torch.device, frames: int) -> dict[str, Any]:
    from smln.checkpoint import load_checkpoint
    from smln.data_sampling import make_scene
    from smln.rollout import rollout

    model, _ = load_checkpoint(ROOT / "checkpoints" / "full")
    scene = make_scene("tshirt_jacket", "female_average", "02_01_walk", edge_length=0.02, max_frames=frames)
    stamps = []
    for _ in rollout(model, scene.cloth, scene.body, scene.body.faces, num_frames=frames, device=device,
                     fallback=True):
        stamps.append(time.perf_counter())
    ms = [1e3 * (b - a) for a, b in zip(stamps[3:], stamps[4:], strict=False)]  # frames 0-2: skinned, warm-up
    return {"scene": "tshirt_jacket@0.02 on 02_01_walk", "vertices": scene.cloth.num_vertices, "frames": frames,
            "ms_per_frame_median": round(statistics.median(ms), 2), "ms_per_frame_p90": round(
                sorted(ms)[int(0.9 * (len(ms) - 1))], 2)}


def training(device: torch.device, seconds: float) -> dict[str, Any]:
    from smln.train import TrainConfig, Trainer

    base = json.loads((ROOT / "docs" / "results" / "r27_config.json").read_text())
    known = set(TrainConfig.__dataclass_fields__)
    cfg = TrainConfig(**{k: v for k, v in base.items() if k in known})
    cfg.variant, cfg.compile, cfg.validate_every, cfg.save_every = "full", False, 10**9, 10**9
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(cfg, Path(out), device=str(device))
        trainer.init_from(str(ROOT / "checkpoints" / "full"))  # the shipped step count: long rollouts
        trainer.run_episode()  # warm-up (scene cache, allocator)
        steps, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            steps += len(trainer.run_episode())
        wall = time.perf_counter() - t0
    return {"recipe": "docs/results/r27_config.json", "steps": steps, "seconds": round(wall, 1),
            "steps_per_s": round(steps / wall, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (the CPU's work)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--train-seconds", type=float, default=60.0)
    ap.add_argument("--json")
    args = ap.parse_args()
    from smln.geometry import set_threads
    from smln.train import resolve_device

    set_threads(args.threads)
    device = resolve_device(args.device)
    out: dict[str, Any] = {
        "device": str(device), "device_name": torch.cuda.get_device_name(device) if device.type == "cuda"
        else (platform.processor() or platform.machine()), "torch": torch.__version__, "threads": args.threads,
        "cpus": os.cpu_count(),
        "inference": inference(device, args.frames),
        "training": training(device, args.train_seconds),
    }
    text = json.dumps(out, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
