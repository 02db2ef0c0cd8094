"""The GPU paths of training and rollout. The CUDA tests skip, with the reason, on a machine without a GPU (CI);
``scripts/device_check.sh`` runs them on the device machine. The first two run everywhere."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from smln.train import resolve_device, train

CUDA = torch.cuda.is_available()
needs_cuda = pytest.mark.skipif(not CUDA, reason="no CUDA device (run scripts/device_check.sh on a GPU machine)")

TINY = ["--motions", "02_01_walk", "--shapes", "female_average", "--save-every", "2", "--validate-every", "100000",
        "--rollout-max", "3", "--threads", "1", "--seed", "5"]


def _outfit() -> str:
    from smln.data_sampling import outfit_names

    return outfit_names("train")[0]


@pytest.mark.skipif(CUDA, reason="this machine has a GPU")
def test_asking_for_cuda_without_a_gpu_says_so():
    with pytest.raises(RuntimeError, match="no CUDA device"):
        resolve_device("cuda")
    assert resolve_device("cpu") == torch.device("cpu")


def test_scene_cache_puts_every_tensor_of_a_scene_on_its_device():
    from smln.data_sampling import SceneCache

    scene = SceneCache(edge_length=0.035, device="cpu").get(_outfit(), "female_average", "02_01_walk", window=(0, 4))
    seq = scene.body
    assert seq.to("cpu") is seq  # same device: no copy
    tensors = [scene.skinned, seq.vertices, seq.faces, seq.transforms, scene.cloth.rest_vertices, scene.rest.mass]
    assert all(t.device.type == "cpu" for t in tensors)


@needs_cuda
def test_training_on_the_gpu_takes_the_cpu_runs_steps(tmp_path):
    """The same seed on CPU and GPU: the same episodes and noise (drawn on the CPU), the same first losses up to
    float32 reduction order; the GPU run's checkpoint loads on the CPU and its state resumes."""
    common = ["--max-steps", "4", "--outfits", _outfit(), *TINY]
    train(["--out", str(tmp_path / "cpu"), *common])
    gpu = train(["--out", str(tmp_path / "gpu"), "--device", "cuda", *common])
    assert gpu.device.type == "cuda" and all(p.is_cuda for p in gpu.model.parameters())
    assert all(p.is_cuda for p in gpu.ema.parameters())
    import csv

    rows = {name: list(csv.DictReader(open(tmp_path / name / "log.csv"))) for name in ("cpu", "gpu")}
    first_cpu, first_gpu = float(rows["cpu"][0]["total"]), float(rows["gpu"][0]["total"])
    assert abs(first_gpu - first_cpu) <= 1e-3 * abs(first_cpu) + 1e-6
    from smln.checkpoint import load_checkpoint

    model, card = load_checkpoint(tmp_path / "gpu" / "last")
    assert card["training"]["device"].startswith("cuda")
    assert all(torch.isfinite(p).all() and p.device.type == "cpu" for p in model.parameters())
    resumed = train(["--out", str(tmp_path / "gpu"), "--resume", "--device", "cuda", "--max-steps", "6"])
    assert resumed.step >= 6


@needs_cuda
def test_validation_on_the_gpu_leaves_the_averaged_model_there(tmp_path):
    trainer = train(["--out", str(tmp_path / "run"), "--device", "cuda", "--max-steps", "1", "--outfits", _outfit(),
                     *TINY])
    trainer.cfg.validation_frames = 6
    trainer.cfg.validation_motion = "02_01_walk"
    val = trainer.validate()
    assert np.isfinite(val["val_score"])
    assert all(p.is_cuda for p in trainer.ema.parameters())
    trainer.update_ema()  # the next EMA update mixes tensors of one device


@needs_cuda
def test_rollout_on_the_gpu_matches_the_cpu():
    from smln.checkpoint import load_checkpoint
    from smln.data_sampling import make_scene
    from smln.rollout import rollout

    root = Path(__file__).resolve().parents[1]
    model, _ = load_checkpoint(root / "checkpoints" / "full")
    scene = make_scene("tshirt_jacket", "female_average", "02_01_walk", edge_length=0.035, max_frames=12)
    runs = {}
    for dev in ("cpu", "cuda"):
        frames = list(rollout(model, scene.cloth, scene.body, scene.body.faces, num_frames=12, device=dev))
        runs[dev] = np.stack([f.garment_positions for f in frames])
    assert np.isfinite(runs["cuda"]).all()
    assert np.abs(runs["cuda"] - runs["cpu"]).max() < 2e-3  # m, after 10 autoregressive steps in float32


DDP_CHECK = (
    "import sys, torch, torch.distributed as dist\n"
    "from smln.train import close_distributed, train\n"
    "t = train(sys.argv[1:])\n"
    "flat = torch.cat([p.detach().flatten() for p in t.model.parameters()])\n"
    "flat = flat.cpu() if dist.get_backend() == 'gloo' else flat\n"
    "gathered = [torch.zeros_like(flat) for _ in range(dist.get_world_size())]\n"
    "dist.all_gather(gathered, flat)\n"
    "assert all(torch.equal(gathered[0], g) for g in gathered), 'ranks diverged'\n"
    "assert t.device.type == 'cuda' and t.step >= 3\n"
    "print('DDP-OK', dist.get_rank(), t.device, t.step)\n"
    "close_distributed()\n"
)


def _torchrun(tmp_path: Path, device: str, backend: str) -> None:
    script = tmp_path / "ddp_check.py"
    script.write_text(DDP_CHECK)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", str(script),
           "--out", str(tmp_path / "run"), "--device", device, "--dist-backend", backend, "--max-steps", "3",
           "--outfits", _outfit(), *TINY]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=Path(__file__).parents[1])
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    assert done.stdout.count("DDP-OK") == 2
    assert (tmp_path / "run" / "last.safetensors").exists()


@needs_cuda
def test_two_processes_share_one_gpu_with_gloo(tmp_path):
    _torchrun(tmp_path, "cuda:0", "gloo")


@needs_cuda
@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="nccl needs one GPU per process")
def test_torchrun_with_nccl_on_two_gpus(tmp_path):
    _torchrun(tmp_path, "cuda", "auto")
