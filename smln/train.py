"""Self-supervised training of SMLN (paper §3.3, §4): motion clips, outfits and physics losses, no garment data.

Each *episode* picks an outfit from the training split, a body-shape preset, a training clip and a start frame,
initialises the garments by skinning (x_{t-1}, x_t from the skinned frames t0-1, t0) and rolls the model out
autoregressively. After every step the losses of Eq. 17 (+ inertia and body collision) are back-propagated
through that one step and the optimiser steps; the history is detached (HOOD). The episode length grows during
training (``rollout_start`` -> ``rollout_max``), so later episodes train on the model's own long-rollout states,
which is what long rollouts need to stay stable. A fixed validation rollout on a training clip is
tracked (120 frames); the best checkpoint by that rollout is kept.

Run ``smln train --variant full --minutes 60 --out runs/full``; ``--resume`` continues bit-for-bit from the last
saved state (model, optimiser, normaliser statistics, RNG streams, step). Under
``torchrun --nproc_per_node=N`` the same entry point trains with DistributedDataParallel (gloo on CPU, nccl on
GPU); each rank samples its own episodes, gradients are averaged.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from smln.body import BODY_SHAPES
from smln.data_sampling import Scene, SceneCache
from smln.geometry import set_threads, vertex_normals
from smln.graph import LEGACY_BODY_EDGE_DIM
from smln.losses import BodyStep, LossWeights, layer_pairs, pre_layer_contact_loss, total_loss
from smln.model import SMLN, SMLNConfig
from smln.model.smln import WEIGHTLESS_FIELDS

NOISE_MODES = ("isotropic", "normal")  # TrainConfig.noise_mode, see Trainer.input_noise
START_SAMPLINGS = ("uniform", "speed")  # TrainConfig.start_sampling, see EpisodeSampler.start_probabilities
LAYER_FRICTION_NORMALS = ("weight", "contact")  # TrainConfig.layer_friction_normal, see LossWeights

VARIANTS = {
    # name: (repulsion layer on, repulsion loss on)  -- the paper's Table 3 rows
    "full": (True, True),
    "no_repulsion_layer": (False, True),
    "baseline": (False, False),
}


@dataclass
class TrainConfig:
    """Everything that defines a training run (saved in the run directory and the checkpoint card)."""

    variant: str = "full"
    seed: int = 0
    max_steps: int = 200_000
    minutes: float | None = None
    lr: float = 1e-4
    lr_halving_steps: int = 20_000
    min_lr: float = 1e-6
    lr_origin: int = 0  # the step the lr schedule counts from (``--lr-restart`` sets it to the --init-from step)
    grad_clip: float = 1.0
    edge_length: float = 0.035
    shapes: list[str] = field(default_factory=lambda: list(BODY_SHAPES))
    outfits: list[str] | None = None  # None = the training split
    motions: list[str] | None = None  # None = the training split
    rollout_start: int = 2
    rollout_max: int = 48
    rollout_growth_steps: int = 6000
    noise_std: float = 0.003
    noise_mode: str = "isotropic"  # NOISE_MODES; "normal": along each cloth vertex normal only (session 10)
    noise_normal_std: float = 0.0  # σ of a second offset along the vertex normals, added to the noise above, m
    settle_steps: int = 1
    start_sampling: str = "uniform"  # START_SAMPLINGS; "speed": favour fast phases of a clip (session 21)
    speed_mix: float = 0.5  # with start_sampling "speed": the share of the speed-proportional draw (rest uniform)
    ema_decay: float = 0.999
    init_from: str | None = None
    save_every: int = 250
    snapshot_every: int = 0  # > 0: keep the averaged weights every N steps as OUT/snapshots/step_NNNNNNN (smln select)
    validate_every: int = 500
    validation_frames: int = 120
    validation_outfit: str | None = None
    validation_motion: str = "06_01_walk"
    validation_skin_guard: str = "always"  # smln.rollout.SKIN_GUARDS; "symptomatic": a swing past 0.4 m is no failure
    log_every: int = 10
    threads: int = 1
    compile: bool = False  # the processor through torch.compile (forward and backward; smln.model.compiled)
    repulsion_weight: float | None = None  # None = LossWeights.training() (1e4); sessions 1-2 trained with 1e3
    collision_weight: float | None = None  # None = LossWeights.training() (1e4); session 4 tried 5e4
    stretch_weight: float | None = None  # None = 1 (the paper's λs); > 1 = a stiffer membrane (session 15)
    collision_eps: float | None = None  # None = COLLISION_EPS (3 mm); the body penalty's clearance, m (session 13)
    repulsion_eps: float | None = None  # None = REPULSION_EPS (3 mm); the layers' clearance in the repulsion loss, m
    layer_friction_weight: float | None = None  # None = off; the friction between layers (session 11)
    layer_friction_normal: str = "weight"  # LAYER_FRICTION_NORMALS; "contact": + the repulsion push (session 12)
    layer_friction_radius: float | None = None  # None = repulsion clearance + 2 mm; the layer friction's contact, m
    model: dict[str, Any] = field(default_factory=dict)
    body_push_init: float = 1.0  # an --init-from run that adds the body repulsion stage starts it at this push
    freeze_body_stage: bool = False  # the body stage of the repulsion layer keeps its initial weights (a fixed push)
    pre_layer_repulsion: float = 0.0  # > 0: the repulsion loss also on x̂, before the layer, x this factor (session 40)
    pre_layer_collision: float = 0.0  # > 0: the body penalty also on x̂, before the layer, x this factor (session 40)

    def weights(self) -> LossWeights:
        """The loss weights of this variant: :meth:`LossWeights.training`, repulsion off for ``baseline`` (the
        friction between layers, when set, is a friction term and stays on for all three variants)."""
        w = LossWeights.training()
        if self.repulsion_weight is not None:
            w.repulsion = self.repulsion_weight
        if self.collision_weight is not None:
            w.collision = self.collision_weight
        if self.stretch_weight is not None:
            if not 0.0 < self.stretch_weight <= 100.0:
                raise ValueError(f"stretch_weight must be in (0, 100], got {self.stretch_weight!r}")
            w.stretch = self.stretch_weight
        for clearance in ("collision_eps", "repulsion_eps", "layer_friction_radius"):  # m, same name in LossWeights
            value = getattr(self, clearance)
            if value is not None:
                if not 0.0 <= value < 0.05:
                    raise ValueError(f"{clearance} must be in [0, 0.05) m, got {value!r}")
                setattr(w, clearance, value)
        if self.layer_friction_weight is not None:
            w.layer_friction = self.layer_friction_weight
        if self.layer_friction_normal not in LAYER_FRICTION_NORMALS:
            raise ValueError(f"layer_friction_normal must be one of {LAYER_FRICTION_NORMALS}, "
                             f"got {self.layer_friction_normal!r}")
        w.layer_friction_contact = self.layer_friction_normal == "contact"
        if not VARIANTS[self.variant][1]:
            w.repulsion = 0.0
        for name in ("pre_layer_repulsion", "pre_layer_collision"):
            factor = getattr(self, name)
            if not 0.0 <= factor <= 100.0:
                raise ValueError(f"{name} must be in [0, 100], got {factor!r}")
            if factor and not VARIANTS[self.variant][0]:
                raise ValueError(f"{name} reads the prediction before the repulsion layer; variant "
                                 f"{self.variant!r} has no layer (its prediction is already what the losses read)")
        return w

    def model_config(self) -> SMLNConfig:
        cfg = dict(self.model)
        cfg["use_repulsion_layer"] = VARIANTS[self.variant][0]
        return SMLNConfig.from_dict(cfg) if cfg else SMLNConfig(use_repulsion_layer=VARIANTS[self.variant][0])


# ----------------------------------------------------------------------------------------------- distributed


def _dist_info() -> tuple[int, int]:
    return int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))


DIST_BACKENDS = ("auto", "nccl", "gloo")
"""``auto``: nccl on GPUs, gloo on CPUs. ``gloo`` on GPUs lets several processes share one GPU (nccl needs one GPU
per process): each process does its own CPU-side work (KD-tree queries, graph building) on its own core."""


def _init_distributed(device: torch.device, backend: str = "auto") -> bool:
    rank, world = _dist_info()
    if world <= 1:
        return False
    if backend not in DIST_BACKENDS:
        raise ValueError(f"unknown distributed backend {backend!r}; choose one of {', '.join(DIST_BACKENDS)}")
    import torch.distributed as dist

    if not dist.is_initialized():
        if backend == "auto":
            backend = "nccl" if device.type == "cuda" else "gloo"
        dist.init_process_group(backend)
    return True


def resolve_device(device: str | torch.device) -> torch.device:
    """The device this process trains on. ``"cuda"`` without an index means, under ``torchrun``, the GPU of this
    process's ``LOCAL_RANK`` (one GPU per process, as nccl needs), else GPU 0; it is also made the current GPU.

    Raises:
        RuntimeError: a CUDA device is asked for and PyTorch sees none.
    """
    dev = torch.device(device)
    if dev.type != "cuda":
        return dev
    if not torch.cuda.is_available():
        raise RuntimeError(f"--device {device}: PyTorch sees no CUDA device (torch {torch.__version__})")
    if dev.index is None:
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    torch.cuda.set_device(dev)
    return dev


# ------------------------------------------------------------------------------------------------- sampling


class EpisodeSampler:
    """Draws (outfit, shape, clip, start frame, length) from a seeded numpy generator."""

    def __init__(self, cfg: TrainConfig, seed: int) -> None:
        from smln.data_sampling import outfit_names
        from smln.motion import list_clips

        self.outfits = cfg.outfits or outfit_names("train")
        self.motions = cfg.motions or list_clips("train")
        self.shapes = cfg.shapes
        self.rng = np.random.default_rng(seed)
        self.cfg = cfg
        self._speeds: dict[tuple[str, str], np.ndarray] = {}

    def rollout_length(self, step: int) -> int:
        c = self.cfg
        frac = min(1.0, step / max(1, c.rollout_growth_steps))
        return int(round(c.rollout_start + frac * (c.rollout_max - c.rollout_start)))

    def draw(self, step: int, cache: SceneCache) -> tuple[Scene, int, int]:
        """(scene cut to the episode's frames, first step's frame index in it, episode length)."""
        outfit = self.outfits[self.rng.integers(len(self.outfits))]
        shape = self.shapes[self.rng.integers(len(self.shapes))]
        motion = self.motions[self.rng.integers(len(self.motions))]
        seq = cache.body(shape, motion)
        num_frames = seq.num_frames
        length = self.rollout_length(step)
        last_start = max(1, num_frames - 2 - length)
        if self.cfg.start_sampling == "speed":
            p = self.start_probabilities((shape, motion), seq.vertices, length, last_start)
            start = 1 + int(self.rng.choice(last_start, p=p))
        else:
            start = int(self.rng.integers(1, last_start + 1))
        length = min(length, num_frames - 1 - start)
        # only the episode's frames are skinned: the scene is cut to [start - 1, start + length]
        scene = cache.get(outfit, shape, motion, window=(start - 1, start + length + 1))
        return scene, 1, length

    def start_probabilities(self, key: tuple[str, str], body_vertices: torch.Tensor, length: int,
                            last_start: int) -> np.ndarray:
        """(last_start,) float64 probabilities of the start frames 1 .. last_start for ``start_sampling="speed"``.

        A mixture: ``speed_mix`` of it proportional to the body's mean vertex speed over the episode's frames
        start .. start + length (m/frame), the rest uniform. Fast phases (jumps, landings, pirouettes) are where
        the rollouts penetrate the body and tangle (session 21: per-frame H-Coll of the test rollouts follows the
        body speed of the 10 frames before with correlation 0.49-0.71), and a uniform start samples them rarely.
        Session 21's r28 (half of the starts drawn this way, 26k steps) changed no test figure significantly
        (docs/RESULTS.md), so ``uniform`` stays the default.

        Args:
            key: (shape, motion), the cache key of the clip's per-frame speeds.
            body_vertices: (T, Vb, 3) the clip's body vertices, meters.
            length: episode length in steps; last_start: the last allowed start frame (>= 1).
        """
        speed = self._speeds.get(key)
        if speed is None:
            from smln.motion.posing import body_speed

            speed = self._speeds[key] = body_speed(body_vertices)
        t = speed.shape[0]
        csum = np.concatenate([[0.0], np.cumsum(speed)])
        starts = np.arange(1, last_start + 1)
        stops = np.minimum(starts + length + 1, t)  # frames start .. start + length (the episode's body frames)
        window = (csum[stops] - csum[starts]) / np.maximum(stops - starts, 1)
        uniform = np.full(last_start, 1.0 / last_start)
        total = window.sum()
        if not total > 0:  # a still clip: nothing to favour
            return uniform
        mix = self.cfg.speed_mix
        p = mix * window / total + (1.0 - mix) * uniform
        return p / p.sum()


# ------------------------------------------------------------------------------------------------- training


class Trainer:
    """Owns the model, optimiser, sampler, logs and checkpoints of one run."""

    def __init__(self, cfg: TrainConfig, out_dir: Path, device: str = "cpu", dist_backend: str = "auto") -> None:
        if cfg.variant not in VARIANTS:
            raise ValueError(f"unknown variant {cfg.variant!r}; choose one of {', '.join(VARIANTS)}")
        if cfg.noise_mode not in NOISE_MODES:
            raise ValueError(f"unknown noise_mode {cfg.noise_mode!r}; choose one of {', '.join(NOISE_MODES)}")
        if cfg.start_sampling not in START_SAMPLINGS:
            raise ValueError(f"unknown start_sampling {cfg.start_sampling!r}; choose one of "
                             f"{', '.join(START_SAMPLINGS)}")
        if not 0.0 <= cfg.speed_mix <= 1.0:
            raise ValueError(f"speed_mix must be in [0, 1], got {cfg.speed_mix!r}")
        if cfg.noise_std < 0 or cfg.noise_normal_std < 0:
            raise ValueError(f"input noise σ must be >= 0 (noise_std {cfg.noise_std}, noise_normal_std "
                             f"{cfg.noise_normal_std})")
        from smln.rollout import SKIN_GUARDS

        if cfg.validation_skin_guard not in SKIN_GUARDS:  # a config file's typo, caught before any step
            raise ValueError(f"unknown validation_skin_guard {cfg.validation_skin_guard!r}; choose one of "
                             f"{', '.join(SKIN_GUARDS)}")
        self.cfg = cfg
        self.out = Path(out_dir)
        self.device = resolve_device(device)
        self.distributed = _init_distributed(self.device, dist_backend)
        self.rank, self.world = _dist_info()
        torch.manual_seed(cfg.seed)
        self.model = SMLN(cfg.model_config()).to(self.device)
        if cfg.freeze_body_stage:
            if not self.model.config.body_repulsion:
                raise ValueError("freeze_body_stage needs a model config with body_repulsion")
            # no gradient, so Adam, the clipping and DDP leave the stage alone; --init-from still sets its weights
            self.model.body_repulsion.requires_grad_(False)
        self.net: torch.nn.Module = self.model
        if cfg.compile:  # a shallow copy sharing the weights: self.model (saved, averaged) keeps its module tree
            from smln.model.compiled import with_compiled_processor

            self.net = with_compiled_processor(self.model, training=True)
        if self.distributed:
            from torch.nn.parallel import DistributedDataParallel

            ids = [self.device.index] if self.device.type == "cuda" else None
            self.net = DistributedDataParallel(self.net, device_ids=ids, find_unused_parameters=True)
        # foreach: one fused kernel per step over all parameter tensors instead of a Python loop over them (CPU too)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, foreach=True)
        # exponential moving average of the weights (decay 0.999: ~1k-step horizon); validation and the saved
        # checkpoints use it. Single steps move the raw weights enough to flip a 120-frame rollout between
        # stable and diverging (the first runs' validation curves); the average is much steadier.
        self.ema = SMLN(cfg.model_config()).to(self.device)
        self.ema.load_state_dict(self.model.state_dict())
        self.ema.requires_grad_(False)
        self.cache_tensor_lists()
        self.sampler = EpisodeSampler(cfg, cfg.seed * 1000 + self.rank)
        self.noise = torch.Generator().manual_seed(cfg.seed * 1000 + self.rank + 1)
        self.cache = SceneCache(self.model, edge_length=cfg.edge_length, device=self.device)
        self.weights = cfg.weights()
        self.step = 0
        self.wall = 0.0
        self.best_score = math.inf
        self.history: list[dict[str, float]] = []
        self.parent: dict[str, Any] | None = None  # the checkpoint this run was initialised from (--init-from)

    # -- one autoregressive step -------------------------------------------------------------------------
    def train_step(self, scene: Scene, t: int, x_prev: torch.Tensor, x_cur: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """Predict x_{t+1} from (x_{t-1}, x_t), back-propagate the losses of this step, step the optimiser."""
        topo = scene.topology
        body_cur, body_next = scene.body.vertices[t], scene.body.vertices[t + 1]
        pinned_next = scene.skinned[t + 1]
        if self.cfg.noise_std > 0 or self.cfg.noise_normal_std > 0:
            eps = self.input_noise(scene, x_cur)
            x_prev, x_cur = x_prev + eps, x_cur + eps
        body = BodyStep.from_vertices(body_cur, body_next, scene.body.faces)
        graph = topo.build(x_prev, x_cur, body_cur, body_next, pinned_next, body_normals_next=body.normals_next,
                           body_tree_next=body.tree_next)
        p, a, extras = self.net(graph, topo)
        x_next = extras["x_next"]
        pre_rep, pre_col = self.cfg.pre_layer_repulsion, self.cfg.pre_layer_collision
        pairs = layer_pairs(x_cur.detach(), scene.rest) if pre_rep and scene.rest.num_layers > 1 else None
        loss, terms = total_loss(x_prev, x_cur, x_next, body, scene.rest, self.weights, pairs=pairs)
        if pre_rep or pre_col:  # the network's own prediction x̂ (pinned vertices at their targets), before the layer
            x_hat = torch.where(topo.pinned.unsqueeze(-1), x_next, extras["x_hat"])
            pre_loss, pre_terms = pre_layer_contact_loss(x_hat, body, scene.rest, self.weights, pre_rep, pre_col,
                                                         pairs=pairs)
            loss = loss + pre_loss
            terms.update(pre_terms)
            terms["total"] = float(loss.detach())
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self._params, self.cfg.grad_clip, foreach=True)
        for group in self.opt.param_groups:
            group["lr"] = self.learning_rate()
        self.opt.step()
        self.update_ema()
        self.step += 1
        terms["grad_norm"] = float(grad_norm)
        terms["repulsion_mean"] = float(a.detach().norm(dim=-1).mean())
        return x_next.detach(), terms

    def input_noise(self, scene: Scene, x_cur: torch.Tensor) -> torch.Tensor:
        """(V, 3) float32 meters: the offset added to both input states (x_{t-1}, x_t; velocity unchanged), zero
        on pinned vertices. ``isotropic`` (HOOD's): N(0, σ²) per coordinate. ``normal``: N(0, σ²) along each
        vertex's unit normal of x_t, so the offset moves vertices into and out of the layer beneath and the body
        (what the collision terms teach the network to undo) while edge lengths change only to second order
        (an isotropic offset stretches and compresses edges by ~σ, which the stretch term then trains the
        network to correct within one step). ``noise_normal_std`` > 0 adds a second offset, N(0, σn²) along the
        normals, drawn after the first: e.g. 1.5 mm isotropic + 2.5 mm normal keeps some tangential noise (which
        helps sliding layer contact) at a smaller stretch cost."""
        sigma, sigma_normal = self.cfg.noise_std, self.cfg.noise_normal_std
        dev = x_cur.device  # the draws come from the CPU generator (the same numbers on any device), then move
        eps = torch.zeros_like(x_cur)
        if sigma > 0 and self.cfg.noise_mode == "normal":
            amount = (torch.randn((x_cur.shape[0], 1), generator=self.noise) * sigma).to(dev)
            eps = vertex_normals(x_cur, scene.cloth.faces) * amount
        elif sigma > 0:
            eps = (torch.randn(x_cur.shape, generator=self.noise) * sigma).to(dev)
        if sigma_normal > 0:  # ``noise_normal_std``: a second, normal-only offset on top (mixed noise)
            amount = (torch.randn((x_cur.shape[0], 1), generator=self.noise) * sigma_normal).to(dev)
            eps = eps + vertex_normals(x_cur, scene.cloth.faces) * amount
        eps[scene.cloth.pinned] = 0
        return eps

    def learning_rate(self, step: int | None = None) -> float:
        """lr * 0.5^((step - lr_origin) / lr_halving_steps), at least min_lr (the schedule restarts at
        ``lr_origin``; before it, the step counts as the origin)."""
        s = self.step if step is None else step
        k = max(0, s - self.cfg.lr_origin) / self.cfg.lr_halving_steps
        return max(self.cfg.min_lr, self.cfg.lr * 0.5**k)

    def _agree(self, value: float, op: str) -> float:
        """The same value on every rank (min or max), so all ranks take the same number of optimiser steps."""
        if not self.distributed:
            return value
        import torch.distributed as dist

        t = torch.tensor([value], dtype=torch.float64, device=self.device)  # nccl reduces GPU tensors only
        dist.all_reduce(t, op=dist.ReduceOp.MIN if op == "min" else dist.ReduceOp.MAX)
        return float(t.item())

    def run_episode(self) -> list[dict[str, float]]:
        """One episode from skinned states; the first ``settle_steps`` steps relax without momentum (as the
        rollout does, :func:`smln.rollout.rollout`): after them the velocity is reset to the skinning's."""
        scene, start, length = self.sampler.draw(self.step, self.cache)
        length = int(self._agree(length, "min"))
        skinned = scene.skinned
        x_prev, x_cur = skinned[start - 1].clone(), skinned[start].clone()
        logs = []
        for k in range(length):
            t = start + k
            x_next, terms = self.train_step(scene, t, x_prev, x_cur)
            bad = not torch.isfinite(x_next).all() or (x_next - skinned[t + 1]).norm(dim=-1).max() > 1.0
            if self._agree(float(bad), "max") > 0:
                terms["reset"] = 1.0
                logs.append(terms)
                break  # diverged: start a fresh episode from skinning
            if k < self.cfg.settle_steps:
                x_prev, x_cur = x_next - (skinned[t + 1] - skinned[t]), x_next
            else:
                x_prev, x_cur = x_cur, x_next
            logs.append(terms)
        return logs

    def cache_tensor_lists(self) -> None:
        """Keep the tensor lists that the per-step EMA update and gradient clipping walk (``load_state_dict``
        copies in place, so they stay valid): listing them through the module tree every step cost ~6 % of a
        training step."""
        self._params = list(self.model.parameters())
        self._ema_pairs = (list(self.ema.parameters()), [p.detach() for p in self._params])
        self._buffer_pairs = list(zip(self.ema.buffers(), self.model.buffers(), strict=True))
        if len(self._ema_pairs[0]) != len(self._params):
            raise RuntimeError("EMA and model parameters differ")

    @torch.no_grad()
    def update_ema(self) -> None:
        """ema <- decay * ema + (1 - decay) * weights (one foreach lerp over all tensors); buffers (normaliser
        statistics) are copied."""
        ema, weights = self._ema_pairs
        torch._foreach_lerp_(ema, weights, 1.0 - self.cfg.ema_decay)
        for e, b in self._buffer_pairs:
            e.copy_(b)

    def init_from(self, path: str) -> None:
        """Start from a checkpoint's weights (and its step count, so the lr and rollout-length schedules go on
        from there); the optimiser starts fresh. The checkpoint's architecture must match this run's, lack only the
        body-normal edge columns (:func:`~smln.model.migrate.widen_body_edges`), be a shallower version of it
        (:func:`~smln.model.migrate.grow`: more hidden layers per MLP or more steps per schedule visit in the run's
        ``model`` config), or lack only the body stage of the repulsion layer
        (:func:`~smln.model.migrate.add_body_repulsion`); the first two start from the checkpoint's function
        exactly, the last one with the new stage acting as a collision projection. Fields of
        :data:`WEIGHTLESS_FIELDS` may differ: the run's config sets them."""
        from smln.checkpoint import load_checkpoint
        from smln.model.migrate import add_body_repulsion, grow, growth_error, widen_body_edges

        model, card = load_checkpoint(path)
        model = model.to(self.device)
        old_cfg, new_cfg = model.config.to_dict(), self.model.config.to_dict()
        for key in WEIGHTLESS_FIELDS:  # how the weights are used, not which there are: the run's own setting holds
            old_cfg[key] = new_cfg[key]
        if old_cfg == new_cfg:
            self.model.load_state_dict(model.state_dict())
        elif old_cfg == {**new_cfg, "body_normal_features": False}:
            # a checkpoint from before the body-normal edge features: widen it, same function
            widen_body_edges(model, self.model, self.body_normal_samples())
        elif new_cfg["body_repulsion"] and old_cfg == {
                **new_cfg, "body_repulsion": False, "body_repulsion_threshold": old_cfg["body_repulsion_threshold"]}:
            # the run adds the body stage of the repulsion layer: everything else as trained, the stage new
            add_body_repulsion(model, self.model, self.cfg.body_push_init)
        elif (why := growth_error(model.config, self.model.config)) is None:
            # this run's model is deeper (more hidden layers, more steps per visit): grow it, same function
            grow(model, self.model)
        else:
            raise ValueError(f"{path}: architecture differs from this run's model config and is not a growth of it "
                             f"({why})")
        self.ema.load_state_dict(self.model.state_dict())
        tr = card.get("training", {})
        self.step = int(tr.get("steps", 0))
        self.parent = {"path": str(path), "steps": self.step, "wall_time_s": tr.get("wall_time_s"),
                       "hardware": tr.get("hardware"), "loss_weights": card.get("loss_weights"),
                       "initialised_from": card.get("initialised_from")}
        if card.get("averaged_from"):  # a weight average (`smln average`): name its inputs in the lineage
            self.parent["averaged_from"] = [{k: a.get(k) for k in ("path", "sha256", "weight", "steps")}
                                            for a in card["averaged_from"]]

    def body_normal_samples(self, frame_stride: int = 15) -> torch.Tensor:
        """(M, 4) body-normal columns of the body edges of skinned training states (every ``frame_stride``-th
        frame of every training clip, one outfit per clip in turn, all shapes in turn): the statistics that
        :func:`smln.model.migrate.widen_body_edges` gives the normaliser's new columns."""
        s = self.sampler
        rows = []
        for i, motion in enumerate(s.motions):
            scene = self.cache.get(s.outfits[i % len(s.outfits)], s.shapes[i % len(s.shapes)], motion)
            topo, faces = scene.topology, scene.body.faces
            for t in range(1, scene.num_frames - 1, frame_stride):
                body_next = scene.body.vertices[t + 1]
                g = topo.build(scene.skinned[t - 1], scene.skinned[t], scene.body.vertices[t], body_next,
                               scene.skinned[t + 1], body_normals_next=vertex_normals(body_next, faces))
                rows.append(g.body_features[:, LEGACY_BODY_EDGE_DIM:])
        return torch.cat(rows)

    # -- validation ------------------------------------------------------------------------------------------
    def validate(self) -> dict[str, float]:
        from smln.rollout import rollout

        c = self.cfg
        outfit = c.validation_outfit or self.sampler.outfits[0]
        scene = self.cache.get(outfit, "female_average", c.validation_motion)
        frames = min(c.validation_frames, scene.num_frames - 2)
        seq = scene.body.slice(0, frames + 1)
        model = self.ema
        model.eval()
        metrics: list[dict[str, float]] = []
        exploded = 0.0
        try:
            with torch.no_grad():
                for fr in rollout(model, scene.cloth, seq, scene.body.faces, num_frames=frames, fallback=True,
                                  skin_guard=c.validation_skin_guard, device=self.device):
                    metrics.append(fr.metrics)
                    if fr.fallback:
                        exploded = 1.0
                        break
        finally:
            self.model.train()  # rollout() put the evaluated model in eval mode; the trained one stays in train
        keys = ("strain_mean", "h_coll", "l_coll")
        out = {f"val_{k}": float(np.mean([m.get(k, np.nan) for m in metrics])) if metrics else math.nan for k in keys}
        out["val_frames"] = float(len(metrics))
        out["val_exploded"] = exploded
        score = out["val_strain_mean"] + out["val_h_coll"] / 100 + out["val_l_coll"] / 100
        out["val_score"] = score + 10.0 * exploded + (frames - len(metrics)) / max(frames, 1)
        return out

    # -- persistence -------------------------------------------------------------------------------------------
    def state_path(self) -> Path:
        return self.out / "train_state.pt"

    def save_state(self) -> None:
        """Everything needed to continue bit-for-bit (loadable with ``torch.load(weights_only=True)``)."""
        state = {
            "model": self.model.state_dict(),
            "ema": self.ema.state_dict(),
            "optimizer": self.opt.state_dict(),
            "step": self.step,
            "wall": self.wall,
            "best_score": self.best_score,
            "torch_rng": torch.get_rng_state(),
            "noise_rng": self.noise.get_state(),
            "sampler_rng": json.dumps(self.sampler.rng.bit_generator.state),
            "parent": json.dumps(self.parent),
        }
        tmp = self.state_path().with_suffix(".tmp")
        torch.save(state, tmp)
        tmp.replace(self.state_path())

    def load_state(self) -> None:
        state = torch.load(self.state_path(), map_location="cpu", weights_only=True)
        self.model.load_state_dict(state["model"])
        self.ema.load_state_dict(state["ema"] if "ema" in state else state["model"])
        self.opt.load_state_dict(state["optimizer"])
        self.step = int(state["step"])
        self.wall = float(state["wall"])
        self.best_score = float(state["best_score"])
        torch.set_rng_state(state["torch_rng"])
        self.noise.set_state(state["noise_rng"])
        self.sampler.rng.bit_generator.state = json.loads(state["sampler_rng"])
        self.parent = json.loads(state["parent"]) if "parent" in state else None

    def card(self, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        return {
            "variant": self.cfg.variant,
            "training": {**asdict(self.cfg), "steps": self.step, "wall_time_s": round(self.wall, 1),
                         "processes": self.world, "device": str(self.device),
                         "hardware": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
                         "torch": torch.__version__},
            "loss_weights": asdict(self.weights),
            **({"initialised_from": self.parent} if self.parent else {}),
            **(extra or {}),
        }

    def save_checkpoint(self, name: str, extra: dict[str, Any] | None = None) -> Path:
        from smln.checkpoint import save_checkpoint

        path = self.out / name
        save_checkpoint(path, self.ema, card=self.card({"weights": f"exponential moving average of the training "
                                                             f"weights, decay {self.cfg.ema_decay}", **(extra or {})}))
        return path

    # -- logs ----------------------------------------------------------------------------------------------------
    def append_log(self, rows: list[dict[str, float]]) -> None:
        path = self.out / "log.csv"
        keys = ["step", "wall_s", "total", "stretch", "bending", "gravity", "inertia", "collision", "friction",
                "repulsion", "grad_norm", "repulsion_mean", "val_strain_mean", "val_h_coll", "val_l_coll",
                "val_frames", "val_exploded", "val_score", "layer_friction", "pre_repulsion", "pre_collision"]
        new = not path.exists()
        if not new:  # a log begun before a column was added keeps its own columns (resume appends to it)
            with open(path, newline="") as fh:
                keys = next(csv.reader(fh), None) or keys
        with open(path, "a", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
            if new:
                writer.writeheader()
            for r in rows:
                writer.writerow({k: r.get(k, "") for k in keys})

    # -- main loop -----------------------------------------------------------------------------------------------
    def fit(self) -> None:
        from tqdm import tqdm

        cfg = self.cfg
        main = self.rank == 0
        self.out.mkdir(parents=True, exist_ok=True)
        if main:
            (self.out / "config.json").write_text(json.dumps(asdict(cfg), indent=1))
        budget = cfg.minutes * 60 if cfg.minutes else math.inf
        started = time.time() - self.wall
        bar = tqdm(total=cfg.max_steps, initial=self.step, disable=not main, dynamic_ncols=True)
        pending: list[dict[str, float]] = []
        last_save, last_val, last_snapshot = self.step, self.step, self.step
        while self.step < cfg.max_steps and (time.time() - started) < budget:
            t0 = time.time()
            logs = self.run_episode()
            self.wall = time.time() - started
            for i, r in enumerate(logs):
                r["step"] = self.step - len(logs) + i + 1
                r["wall_s"] = round(self.wall, 2)
            pending.extend(logs[:: max(1, cfg.log_every)] if len(logs) > 1 else logs)
            if main and logs:
                last = logs[-1]
                bar.update(len(logs))
                bar.set_postfix(loss=f"{last['total']:.3g}", st=f"{last.get('stretch', 0):.2g}",
                                col=f"{last.get('collision', 0):.2g}", sps=f"{len(logs) / (time.time() - t0):.1f}")
            if self.step - last_val >= cfg.validate_every:
                last_val = self.step
                if main:
                    val = self.validate()
                    pending.append({"step": self.step, "wall_s": round(self.wall, 2), **val})
                    if val["val_score"] < self.best_score:
                        self.best_score = val["val_score"]
                        self.save_checkpoint("best", {"validation": val})
            if cfg.snapshot_every > 0 and self.step - last_snapshot >= cfg.snapshot_every:
                last_snapshot = self.step
                if main:
                    self.save_checkpoint(f"snapshots/step_{self.step:07d}")
            if self.step - last_save >= cfg.save_every:
                last_save = self.step
                if main:
                    self.append_log(pending)
                    pending = []
                    self.save_state()
                    self.save_checkpoint("last")
        if main:
            self.append_log(pending)
            self.save_state()
            self.save_checkpoint("last")
            plot_log(self.out / "log.csv", self.out / "loss.png")
        bar.close()


def running_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average of ``values`` over ``window`` samples, averaging only the samples that exist.

    Near the ends the window is cut short instead of padded with zeros, so a constant series stays constant
    (``np.convolve(..., mode="same")`` would bend its first and last ``window // 2`` samples towards 0).

    Args:
        values: (N,) float series; window: samples per average, >= 1.
    Returns:
        (N,) float64.
    """
    values = np.asarray(values, dtype=np.float64)
    if window <= 1 or len(values) == 0:
        return values.copy()
    kernel = np.ones(window)
    sums = np.convolve(values, kernel, mode="same")
    counts = np.convolve(np.ones_like(values), kernel, mode="same")
    return sums / counts


def plot_log(csv_path: Path, png_path: Path) -> None:
    """PNG of every loss term (moving average) and the validation curves of a run's log; x = optimiser step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    rows = list(csv.DictReader(open(csv_path)))
    if not rows:
        return
    terms = ["total", "stretch", "bending", "gravity", "inertia", "collision", "friction", "repulsion"]
    if any(r.get("layer_friction") not in ("", None) for r in rows):
        terms.append("layer_friction")
    vals = ["val_strain_mean", "val_h_coll", "val_l_coll", "val_frames"]
    keys = terms + vals
    fig, axes = plt.subplots(3 + (len(terms) > 8), 4, figsize=(16, 10 + 3.3 * (len(terms) > 8)))
    for ax in axes.flat[len(keys):]:
        ax.set_visible(False)
    step_format = FuncFormatter(lambda s, _: f"{s / 1000:g}k" if abs(s) >= 1000 else f"{s:g}")
    for ax, key in zip(axes.flat, keys, strict=False):
        pts = [(float(r["step"]), float(r[key])) for r in rows if r.get(key) not in ("", None)]
        if not pts:
            ax.set_visible(False)
            continue
        s, v = np.array(pts).T
        if not key.startswith("val_") and len(v) > 20:
            v = running_mean(v, max(1, len(v) // 50))
        ax.plot(s, v)
        ax.set_title(key)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=5))
        ax.xaxis.set_major_formatter(step_format)
        if key in ("stretch", "collision", "repulsion", "bending", "friction", "layer_friction") and (v > 0).all():
            ax.set_yscale("log")
    fig.tight_layout()
    fig.savefig(png_path, dpi=70)
    plt.close(fig)


def parse_args(argv: list[str] | None = None) -> tuple[TrainConfig, argparse.Namespace]:
    p = argparse.ArgumentParser(prog="smln train", description="Self-supervised training of SMLN.")
    p.add_argument("--config", help="JSON file with TrainConfig fields (flags override it)")
    p.add_argument("--variant", choices=list(VARIANTS))
    p.add_argument("--out", required=True, help="run directory (log.csv, loss.png, train_state.pt, best/, last/)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/train_state.pt")
    p.add_argument("--force", action="store_true",
                   help="start a new run in an OUT that already holds one (its train_state.pt, last checkpoint and "
                        "log.csv are overwritten; its best and snapshots/ stay until the new run replaces them); "
                        "without it such an OUT is refused unless --resume")
    p.add_argument("--minutes", type=float,
                   help="wall-clock budget of the whole run; it ends cleanly after it (a --resume'd run counts the "
                        "time it has already spent: to go on for 60 more minutes, add 60 to its last budget)")
    p.add_argument("--max-steps", type=int,
                   help="stop once this many optimiser steps are reached; checked between episodes, so a run ends "
                        "at the end of the episode that crosses it (at most --rollout-max steps over), which keeps "
                        "a stopped-and-resumed run bit-for-bit equal to an uninterrupted one")
    p.add_argument("--seed", type=int)
    p.add_argument("--lr", type=float)
    p.add_argument("--lr-halving-steps", type=int, help="steps per halving of the lr (default 20000)")
    p.add_argument("--lr-restart", action="store_true",
                   help="with --init-from: the lr schedule starts again at --lr from the checkpoint's step "
                        "(a warm restart; the step count and the rollout-length schedule go on)")
    p.add_argument("--threads", type=int)
    p.add_argument("--noise-std", type=float,
                   help="σ of the Gaussian noise on the input positions, m (default 3e-3, HOOD's; session 8's 1e-3 "
                        "run: 1.1 points less mean strain, 0.5 more L-Coll, docs/RESULTS.md)")
    p.add_argument("--noise-mode", choices=NOISE_MODES,
                   help="direction of that noise (Trainer.input_noise): isotropic (default, HOOD's) or normal (along "
                        "each cloth vertex normal: into and out of the layers and the body, edge lengths ~unchanged)")
    p.add_argument("--noise-normal-std", type=float,
                   help="σ of a second input-noise offset along the vertex normals, added to the one above, m "
                        "(default 0)")
    p.add_argument("--start-sampling", choices=START_SAMPLINGS,
                   help="how an episode's start frame is drawn in its clip: uniform (default) or speed (a mixture "
                        "favouring the clip's fast phases by the body's mean vertex speed; --speed-mix sets the share)")
    p.add_argument("--speed-mix", type=float,
                   help="with --start-sampling speed: share of the speed-proportional draw, the rest uniform "
                        "(default 0.5)")
    p.add_argument("--compile", action="store_true", default=None,
                   help="run the processor through torch.compile, forward and backward (13-18 %% faster steps on "
                        "CPU after a one-off compilation of ~2 minutes; eager if compilation fails)")
    p.add_argument("--device", default="cpu",
                   help="cpu, cuda or cuda:N (under torchrun, cuda means each process's LOCAL_RANK GPU, with nccl)")
    p.add_argument("--dist-backend", choices=DIST_BACKENDS, default="auto",
                   help="under torchrun: auto (nccl on GPUs, gloo on CPUs); gloo with --device cuda:0 lets several "
                        "processes share one GPU")
    p.add_argument("--outfits", nargs="+")
    p.add_argument("--motions", nargs="+")
    p.add_argument("--shapes", nargs="+")
    p.add_argument("--save-every", type=int)
    p.add_argument("--validate-every", type=int)
    p.add_argument("--snapshot-every", type=int,
                   help="keep the averaged weights every N steps as OUT/snapshots/step_NNNNNNN.{safetensors,json} "
                        "(default 0: off), for `smln select` to score on more scenes than the validation clip")
    p.add_argument("--rollout-max", type=int)
    p.add_argument("--init-from", help="start from this checkpoint's weights and step count (fresh optimiser)")
    p.add_argument("--repulsion-weight", type=float,
                   help="λr of the repulsion loss (default: LossWeights.training(), 1e4; ignored by baseline)")
    from smln.rollout import SKIN_GUARDS

    p.add_argument("--validation-skin-guard", choices=SKIN_GUARDS,
                   help="the validation rollout's skinned-distance guard (smln.rollout.SKIN_GUARDS; default always: "
                        "a jacket swinging past 0.4 m in the pirouette counts as a divergence)")
    p.add_argument("--layer-friction-weight", type=float,
                   help="weight of the friction between adjacent layers (smln.losses.friction."
                        "layer_friction_energy; default off; 1.5 = the body friction's λf)")
    p.add_argument("--layer-friction-normal", choices=LAYER_FRICTION_NORMALS,
                   help="the layer friction's normal force: weight (m g, default) or contact (m g + the repulsion "
                        "loss's push, lagged; baseline has none and keeps the weight)")
    p.add_argument("--layer-friction-radius", type=float,
                   help="contact distance of the layer friction, m (default: the repulsion clearance + 2 mm, "
                        "smln.losses.friction.layer_friction_radius; sessions 27-29 ran with a fixed 0.005)")
    p.add_argument("--collision-weight", type=float,
                   help="weight of the cubic body-collision penalty (default: LossWeights.training(), 1e4)")
    p.add_argument("--stretch-weight", type=float,
                   help="weight λs of the StVK stretch energy (default 1, the paper's): 2 = a membrane twice as stiff "
                        "in the training loss (session 15's lever on mean edge strain)")
    p.add_argument("--collision-eps", type=float,
                   help="clearance ε of that penalty, m (default smln.losses.collision.COLLISION_EPS, 3e-3): the "
                        "body term pushes cloth out to ε, H-Coll counts it inside the body at 0")
    p.add_argument("--repulsion-eps", type=float,
                   help="clearance ε between adjacent layers in the repulsion loss (and the layer friction's contact "
                        "push), m (default smln.losses.repulsion.REPULSION_EPS, 3e-3; ignored by baseline)")
    p.add_argument("--body-push-init", type=float,
                   help="with --init-from a checkpoint without the body stage of the repulsion layer and a model "
                        "config with body_repulsion: the stage starts pushing this fraction of the way to its "
                        "threshold (default 1 = a collision projection; smln.model.migrate.add_body_repulsion)")
    p.add_argument("--freeze-body-stage", action="store_true", default=None,
                   help="the body stage of the repulsion layer is not trained: it keeps the push it starts with "
                        "(--body-push-init with --init-from, else a projection onto its threshold) and the rest of "
                        "the network learns around it")
    p.add_argument("--pre-layer-repulsion", type=float,
                   help="variant full: the repulsion loss read also on the network's prediction before the repulsion "
                        "layer (x̂), weighted by this factor times λr (default 0: off, the paper's objective)")
    p.add_argument("--pre-layer-collision", type=float,
                   help="variant full: the body penalty read also on x̂, before the layer's body stage, weighted by "
                        "this factor times its weight (default 0: off)")
    args = p.parse_args(argv)
    base: dict[str, Any] = {}
    run_cfg = Path(args.out) / "config.json"
    if args.resume and run_cfg.exists():
        base = json.loads(run_cfg.read_text())
    elif args.config:
        base = json.loads(Path(args.config).read_text())
    cfg = TrainConfig(**base)
    for flag, key in (("variant", "variant"), ("minutes", "minutes"), ("max_steps", "max_steps"), ("seed", "seed"),
                      ("lr", "lr"), ("lr_halving_steps", "lr_halving_steps"),
                      ("threads", "threads"), ("outfits", "outfits"), ("motions", "motions"),
                      ("shapes", "shapes"), ("save_every", "save_every"), ("validate_every", "validate_every"),
                      ("snapshot_every", "snapshot_every"),
                      ("rollout_max", "rollout_max"), ("init_from", "init_from"),
                      ("repulsion_weight", "repulsion_weight"), ("collision_weight", "collision_weight"),
                      ("stretch_weight", "stretch_weight"),
                      ("collision_eps", "collision_eps"), ("repulsion_eps", "repulsion_eps"),
                      ("noise_std", "noise_std"), ("noise_mode", "noise_mode"), ("compile", "compile"),
                      ("start_sampling", "start_sampling"), ("speed_mix", "speed_mix"),
                      ("noise_normal_std", "noise_normal_std"), ("layer_friction_weight", "layer_friction_weight"),
                      ("layer_friction_normal", "layer_friction_normal"),
                      ("layer_friction_radius", "layer_friction_radius"),
                      ("validation_skin_guard", "validation_skin_guard"), ("body_push_init", "body_push_init"),
                      ("freeze_body_stage", "freeze_body_stage"),
                      ("pre_layer_repulsion", "pre_layer_repulsion"), ("pre_layer_collision", "pre_layer_collision")):
        if getattr(args, flag) is not None:
            setattr(cfg, key, getattr(args, flag))
    return cfg, args


RUN_FILES = ("train_state.pt", "last.safetensors", "log.csv")
"""Files whose presence in ``--out`` marks a run there (what a new run would overwrite)."""


def refuse_existing_run(out: Path, resume: bool, force: bool) -> None:
    """A new run (no ``--resume``) must not overwrite a run already in ``out`` unless forced.

    Raises:
        FileExistsError: naming the run's files and the two ways on (``--resume``, ``--force``).
    """
    if resume or force:
        return
    found = [name for name in RUN_FILES if (out / name).exists()]
    if found:
        raise FileExistsError(f"{out} already holds a training run ({', '.join(found)}); pass --resume to continue it, "
                              "--force to start over in it (its files are overwritten), or choose another --out")


def train(argv: list[str] | None = None) -> Trainer:
    cfg, args = parse_args(argv)
    refuse_existing_run(Path(args.out), args.resume, args.force)
    set_threads(cfg.threads)
    trainer = Trainer(cfg, Path(args.out), device=args.device, dist_backend=args.dist_backend)
    if args.resume:
        if not trainer.state_path().exists():
            raise FileNotFoundError(f"nothing to resume: {trainer.state_path()} does not exist")
        trainer.load_state()
    elif cfg.init_from:
        trainer.init_from(cfg.init_from)
        if args.lr_restart:
            cfg.lr_origin = trainer.step
    elif args.lr_restart:
        raise ValueError("--lr-restart needs --init-from")
    trainer.fit()
    return trainer


def close_distributed(wait_for_peers: bool = True) -> None:
    """Tear down the process group a distributed run opened (no-op otherwise). Without it a gloo rank can abort at
    interpreter exit ("terminate called without an active exception") after its work is done.

    With ``wait_for_peers`` the ranks first meet at a barrier, so none closes its connections while a peer still has
    a collective in flight; pass False on an error path (a peer that failed or is stuck in another collective would
    never arrive). Drop the trainer (its DDP wrapper holds the group) before calling this, so the gloo threads are gone
    before the interpreter's finalisation."""
    import gc

    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        gc.collect()
        if wait_for_peers:
            dist.barrier()
        dist.destroy_process_group()
        gc.collect()


def _train_and_close(argv: list[str] | None) -> None:
    """Train, then tear the process group down (meeting the peers only when training finished)."""
    finished = False
    try:
        train(argv)
        finished = True
    finally:
        close_distributed(wait_for_peers=finished)


def cli_main(args: argparse.Namespace) -> None:
    _train_and_close(args.argv)


if __name__ == "__main__":
    _train_and_close(None)
