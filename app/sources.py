"""What the viewer can show: outfits, clips, body shapes, checkpoints, and the frame sources of each variant.

A *setting* (outfit, clip, body shape) is loaded once into a :class:`Scenario` (body, posed clip, cloth); each
*variant* (a checkpoint or plain skinning) turns a scenario into an iterator of
:class:`smln.rollout.RolloutFrame`. Uploaded clips and garments are referred to by keys that start with
``upload:`` (see :mod:`app.uploads`).
"""

from __future__ import annotations

import copy
import threading
import types
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from smln.body import BODY_SHAPES, DEFAULT_SHAPE, lbs, load_body
from smln.cloth import FPS, Cloth
from smln.losses.rest import ClothRest
from smln.metrics import frame_metrics
from smln.motion import BodySequence, list_clips, load_body_sequence, manifest
from smln.rollout import RolloutFrame, rollout

PROJECTIONS: tuple[str, ...] = ("off", "body", "body+layers")
"""Collision-projection choices of :class:`Setting` (``smln.projection``)."""

READING_CHANGES: dict[str, tuple[tuple[str, str], ...]] = {
    "vertex": (("repulsion_pairing", "vertex"),),
    "deeper": (("repulsion_pairing", "deeper"),),
    "layer-nearest": (("repulsion_pairing", "nearest"),),
    "body-edge": (("body_pairing", "edge"),),
    "body-nearest": (("body_pairing", "nearest"),),
    "all-nearest": (("repulsion_pairing", "nearest"), ("body_pairing", "nearest")),
    "body-inside": (("body_pairing", "edge_inside"),),
    "nearest-inside": (("repulsion_pairing", "nearest"), ("body_pairing", "edge_inside")),
    "as-trained": (("repulsion_pairing", "vertex"), ("body_pairing", "edge")),
}
"""What each reading but "checkpoint" changes: :class:`~smln.model.SMLNConfig` fields and their values."""

READINGS: tuple[str, ...] = ("checkpoint", *READING_CHANGES)
"""Repulsion-layer readings of :class:`Setting`: the checkpoint's own, ``SMLNConfig.repulsion_pairing`` set to
"vertex", "deeper" or "nearest" (layer-nearest), the body stage's ``SMLNConfig.body_pairing`` set to "edge",
"nearest" or "edge_inside" (body-inside), both stages' pairing set to "nearest" (all-nearest), the layer's "nearest"
with the body's "edge_inside" (nearest-inside), or the pairings every checkpoint was trained with, "vertex" and
"edge" (as-trained), for the session (same weights; a model without the layer, or without its body stage, is
unchanged by what it lacks)."""

VARIANTS: tuple[str, ...] = ("full", "no_repulsion_layer", "baseline", "skinning")
"""Variant keys in display order: the three checkpoints of the paper's ablation, then plain skinning."""

VARIANT_LABELS: dict[str, str] = {
    "full": "SMLN (full)",
    "no_repulsion_layer": "no repulsion layer",
    "baseline": "baseline",
    "skinning": "skinning only",
}

DEFAULT_CLIP = "02_01_walk"
MAX_FRAMES = 300
"""Frames computed per rollout at most (10 s at 30 fps): bounds the frame cache's memory."""


@dataclass(frozen=True)
class Setting:
    """What is animated: an outfit key, a clip key, a body-shape preset, the collision projection and the repulsion
    layer's reading (strings).

    ``projection`` is one of :data:`PROJECTIONS`: "off" (the learned model alone, as evaluated in the paper),
    "body" or "body+layers" (the post-step of :mod:`smln.projection` after every network step). ``reading`` is one
    of :data:`READINGS`: "checkpoint" (as the card says), "vertex" (paper Eq. 14) or "deeper" (also the closest
    inner triangle point, ``SMLNConfig.repulsion_pairing``), "layer-nearest" (against the inner vertex nearest at
    t+1), "body-edge" or "body-nearest" (the body stage against the body vertex nearest at t or nearest to the
    prediction at t+1, ``SMLNConfig.body_pairing``), "all-nearest" (both stages nearest at t+1), "body-inside" (the
    body stage's edge pairs, then the nearest reading for vertices still inside), "nearest-inside" (layer-nearest and
    body-inside) or "as-trained" (vertex and body-edge).
    """

    outfit: str
    clip: str
    shape: str = DEFAULT_SHAPE
    projection: str = "off"
    reading: str = "checkpoint"


@dataclass
class Scenario:
    """A loaded setting.

    Attributes:
        setting: the :class:`Setting`.
        cloth: the outfit as a :class:`~smln.cloth.Cloth` (layers inner -> outer).
        sequence: posed body clip: ``vertices (T, Vb, 3)``, ``transforms (T, B, 3, 4)``, at 30 fps.
        body_faces: (Fb, 3) int64 numpy body triangles.
        layer_faces: per layer, (F_k, 3) int64 faces indexing into that layer's vertex slice.
        layer_slices: contiguous vertex range of each layer.
        num_frames: frames a rollout produces (clip length capped at :data:`MAX_FRAMES`).
    """

    setting: Setting
    cloth: Cloth
    sequence: BodySequence
    body_faces: np.ndarray
    layer_faces: list[np.ndarray]
    layer_slices: list[slice]
    num_frames: int

    @property
    def layer_names(self) -> list[str]:
        names = list(self.cloth.layer_names)
        return names + [f"layer {k}" for k in range(len(names), len(self.layer_slices))]


def outfit_builder(edge_length: float | None = None) -> tuple[Callable[[str, str], Cloth], list[tuple[str, str]]]:
    """The library's outfit builder and its (name, split) list.

    Args:
        edge_length: garment triangle size, m (default: the training resolution, 3.5 cm, at which the shipped
            checkpoints were trained; 0.02 gives the finer 2 cm garments at about 3x the cost per frame).

    Returns:
        ``(build(name, shape) -> Cloth, [(name, split label), ...])``; the label says whether the outfit's
        garment types were seen in training and whether the outfit itself is a training or a test outfit.
    """
    from smln import garments

    size = garments.TRAINING_EDGE_LENGTH if edge_length is None else edge_length

    def build(name: str, shape: str) -> Cloth:
        return garments.build_outfit(name, shape, edge_length=size).to_cloth()

    labels = {"train": "seen · train", "test_seen": "seen · test", "test_unseen": "unseen"}
    return build, [(name, labels.get(garments.outfit_split(name), garments.outfit_split(name)))
                   for name in garments.OUTFITS]


def find_checkpoints(directory: str | Path | None) -> dict[str, Path]:
    """Checkpoints of the three model variants under ``directory``: ``full/``, ``no_repulsion_layer/``,
    ``baseline/``, each a folder holding a ``.safetensors`` file and its ``.json`` card (or ``full.safetensors``
    + ``full.json`` ... directly in ``directory``).

    Returns:
        variant -> path to pass to :func:`smln.checkpoint.load_checkpoint` (only variants that exist).
    """
    found: dict[str, Path] = {}
    if directory is None:
        return found
    root = Path(directory)
    for variant in VARIANTS[:3]:
        d = root / variant
        if d.with_suffix(".safetensors").exists() and d.with_suffix(".json").exists():
            found[variant] = d.with_suffix(".safetensors")  # a stem: <dir>/<variant>.safetensors + .json
            continue
        if not d.is_dir():
            continue
        if (d / "model.safetensors").exists():
            found[variant] = d
            continue
        tensors = sorted(d.glob("*.safetensors"))
        if tensors and tensors[0].with_suffix(".json").exists():
            found[variant] = tensors[0]
    return found


def skinning_frames(scenario: Scenario, num_frames: int | None = None) -> Iterator[RolloutFrame]:
    """Frames of the "skinning only" variant: the cloth linear-blend-skinned onto the clip, with its metrics.

    Yields:
        :class:`RolloutFrame` per frame (zero accelerations).
    """
    cloth, seq = scenario.cloth, scenario.sequence
    n = scenario.num_frames if num_frames is None else min(num_frames, scenario.num_frames)
    rest = ClothRest.from_cloth(cloth)
    zeros = np.zeros((cloth.num_vertices, 3), np.float32)
    chunk = 16
    for start in range(0, n, chunk):  # a loop over frame chunks, not vertices
        stop = min(n, start + chunk)
        x = lbs(cloth.rest_vertices.float(), cloth.skin_indices, cloth.skin_weights, seq.transforms[start:stop])
        for t in range(start, stop):
            body = seq.vertices[t].numpy()
            fm = frame_metrics(x[t - start], body, rest, body_faces=scenario.body_faces)
            metrics = dict(fm.values) | {"repulsion_mean": 0.0, "repulsion_max": 0.0, "prediction_mean": 0.0}
            yield RolloutFrame(t, x[t - start].numpy(), body, zeros, zeros, fm.layer_penetration,
                               fm.body_penetration, metrics, False)


class Catalog:
    """Names the viewer offers and the loaders behind them (thread-safe, small LRU caches).

    Args:
        checkpoint_dir: directory with ``full/``, ``no_repulsion_layer/``, ``baseline/`` checkpoints (or None).
        uploads: :class:`app.uploads.UploadStore` for ``upload:`` keys (or None).
        device: torch device for the model variants ("cpu" or "cuda").
        max_frames: cap on frames per rollout.
        builder: ``(build(name, shape) -> Cloth, [(name, split), ...])`` (default: :func:`outfit_builder`).
    """

    def __init__(
        self,
        checkpoint_dir: str | Path | None = "checkpoints",
        uploads: Any = None,
        device: str = "cpu",
        max_frames: int = MAX_FRAMES,
        builder: tuple[Callable[[str, str], Cloth], list[tuple[str, str]]] | None = None,
        edge_length: float | None = None,
        precision: str = "float32",
        compiled: bool = False,
    ) -> None:
        self.checkpoint_dir = None if checkpoint_dir is None else Path(checkpoint_dir)
        self.precision = precision  # the models' processor precision (smln.model.precision)
        self.compiled = compiled  # the models' processor through torch.compile (smln.model.compiled)
        self.uploads = uploads
        self.device = device
        self.max_frames = max_frames
        self._build, self._outfits = builder if builder is not None else outfit_builder(edge_length)
        self.checkpoints = find_checkpoints(self.checkpoint_dir)
        self.checkpoint_errors: dict[str, str] = {}
        self._models: dict[str | tuple[str, str], Any] = {}  # variant, or (variant, reading) for a re-read copy
        self._cloths: OrderedDict[tuple[str, str], Cloth] = OrderedDict()
        self._sequences: OrderedDict[tuple[str, str], BodySequence] = OrderedDict()
        self._lock = threading.RLock()

    # ---- names ---------------------------------------------------------------------------------------------
    def outfits(self) -> list[tuple[str, str]]:
        """(label, key) per outfit; the label marks the seen/unseen split; uploaded garments come last."""
        out = [(f"{name} ({split})", name) for name, split in self._outfits]
        if self.uploads is not None:
            out += [(f"{label} (uploaded)", key) for key, label in self.uploads.garments()]
        return out

    def clips(self) -> list[tuple[str, str]]:
        """(label, key) per clip; the label marks the train/test split; uploaded clips come last."""
        out = [(f"{c['name']} ({c['split']})", c["name"]) for c in manifest()]
        if self.uploads is not None:
            out += [(f"{label} (uploaded)", key) for key, label in self.uploads.clips()]
        return out

    @staticmethod
    def shapes() -> list[str]:
        return list(BODY_SHAPES)

    def default_setting(self) -> Setting:
        clips = list_clips()
        clip = DEFAULT_CLIP if DEFAULT_CLIP in clips else clips[0]
        return Setting(self._outfits[0][0], clip, DEFAULT_SHAPE)

    def available_variants(self) -> list[str]:
        """Variants that can run now: the checkpoints found, and skinning."""
        return [v for v in VARIANTS if v == "skinning" or v in self.checkpoints]

    # ---- loading -------------------------------------------------------------------------------------------
    def _lru(self, cache: OrderedDict, key: Any, make: Callable[[], Any], size: int = 4) -> Any:
        with self._lock:
            if key in cache:
                cache.move_to_end(key)
                return cache[key]
        value = make()
        with self._lock:
            cache[key] = value
            while len(cache) > size:
                cache.popitem(last=False)
        return value

    def cloth(self, outfit: str, shape: str) -> Cloth:
        """The outfit (or an uploaded garment) on a body shape."""
        if outfit.startswith("upload:"):
            return self.uploads.cloth(outfit, shape)
        return self._lru(self._cloths, (outfit, shape), lambda: self._build(outfit, shape))

    def sequence(self, clip: str, shape: str) -> BodySequence:
        """The posed body along a shipped or uploaded clip."""
        path = self.uploads.clip_path(clip) if clip.startswith("upload:") else clip
        return self._lru(self._sequences, (clip, shape), lambda: load_body_sequence(path, load_body(shape)))

    def prepare(self, setting: Setting) -> Scenario:
        """Load a setting (seconds at most; cached)."""
        cloth = self.cloth(setting.outfit, setting.shape)
        seq = self.sequence(setting.clip, setting.shape)
        slices = cloth.layer_slices()
        faces = cloth.faces.numpy()
        face_layer = cloth.layer_index.numpy()[faces[:, 0]]
        layer_faces = [faces[face_layer == k] - s.start for k, s in enumerate(slices)]
        return Scenario(setting, cloth, seq, seq.faces.numpy().astype(np.int64), layer_faces, slices,
                        min(seq.num_frames, self.max_frames))

    def model(self, variant: str, reading: str = "checkpoint") -> Any:
        """The checkpoint's model for a variant (loaded once), read with ``reading`` (:data:`READINGS`; a copy of
        the loaded model when it changes the checkpoint's reading)."""
        from smln.checkpoint import load_checkpoint
        from smln.evaluate import apply_body_pairing, apply_repulsion_pairing

        if reading not in READINGS:
            raise ValueError(f"unknown repulsion-layer reading {reading!r} (one of {', '.join(READINGS)})")
        with self._lock:
            if variant not in self._models:
                model, _card = load_checkpoint(self.checkpoints[variant], map_location=self.device)
                self._models[variant] = model
            base = self._models[variant]
            if reading == "checkpoint":
                return base
            appliers = {"repulsion_pairing": apply_repulsion_pairing, "body_pairing": apply_body_pairing}
            changes = READING_CHANGES[reading]
            dry_run = types.SimpleNamespace(config=copy.copy(base.config))
            changed = [appliers[field](dry_run, value) for field, value in changes]  # each, on a copy of the config
            if not any(changed):  # the model already reads that way (or lacks the stage)
                return base
            key = (variant, reading)
            if key not in self._models:
                model = copy.deepcopy(base)
                for field, value in changes:
                    appliers[field](model, value)
                self._models[key] = model
            return self._models[key]

    def frames(self, variant: str, scenario: Scenario) -> Iterator[RolloutFrame]:
        """The frame iterator of one variant on a scenario (model variants fall back to skinning on divergence
        and mark such frames ``fallback=True``)."""
        if variant == "skinning":
            return skinning_frames(scenario)
        if variant not in self.checkpoints:
            raise ValueError(f"no checkpoint for variant {variant!r} under {self.checkpoint_dir}")
        proj = scenario.setting.projection
        model = self.model(variant, scenario.setting.reading)
        return rollout(model, scenario.cloth, scenario.sequence, scenario.body_faces,
                       num_frames=scenario.num_frames, device=self.device, fallback=True, precision=self.precision,
                       compiled=self.compiled, project_body=proj in ("body", "body+layers"),
                       project_layers=proj == "body+layers")


__all__ = ["FPS", "MAX_FRAMES", "PROJECTIONS", "READING_CHANGES", "READINGS", "VARIANTS", "VARIANT_LABELS", "Catalog",
           "Scenario", "Setting"]
