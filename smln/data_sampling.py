"""Training scenes: outfits, body shapes and motion clips, loaded lazily and cached.

A *scene* is one outfit dressed on one body shape moving along one clip: the posed body sequence, the outfit's
:class:`~smln.cloth.Cloth`, the skinned garment trajectory, the network's static graph topology and the losses'
rest state. Building a scene costs a fraction of a second; scenes are kept in a bounded LRU cache.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import torch

from smln.body import load_body
from smln.body.skinning import lbs
from smln.cloth import Cloth
from smln.losses import ClothRest
from smln.motion import BodySequence, load_body_sequence


@dataclass
class Scene:
    """An outfit on a body along a clip.

    Attributes:
        outfit, shape, motion: names.
        cloth: the outfit's flat cloth.
        body: posed body, vertices (T, Vb, 3).
        skinned: (T, V, 3) float32 garment positions under pure skinning (initial states, pinned targets).
        rest: losses' rest state; topology: the model's static graph (or None when built without a model).
    """

    outfit: str
    shape: str
    motion: str
    cloth: Cloth
    body: BodySequence
    skinned: torch.Tensor
    rest: ClothRest
    topology: object | None

    @property
    def num_frames(self) -> int:
        return self.body.num_frames


def outfit_names(split: str | None = None) -> list[str]:
    """Registered outfits of a split: ``"train"``, ``"held_out"``/``"test"`` (both held-out kinds),
    ``"test_seen"``, ``"test_unseen"``, or all (None)."""
    from smln.garments import outfit_registry

    reg = outfit_registry()
    if split is None:
        return list(reg)
    if split in ("test", "held_out"):
        return [n for n, o in reg.items() if o["split"] != "train"]
    if split not in ("train", "test_seen", "test_unseen"):
        raise ValueError(f"unknown outfit split {split!r}")
    return [n for n, o in reg.items() if o["split"] == split]


def build_cloth(outfit: str, shape: str, edge_length: float) -> Cloth:
    """The flat cloth of a named outfit (or a user's garments) on a body shape."""
    from smln.garments import build_outfit

    return build_outfit(outfit, shape=shape, edge_length=edge_length).to_cloth()


def make_scene(
    outfit: str | Cloth,
    shape: str,
    motion: str,
    *,
    edge_length: float = 0.02,
    model=None,
    max_frames: int | None = None,
    body_sequence: BodySequence | None = None,
) -> Scene:
    """Build a scene. ``outfit`` is a registered outfit name or a ready :class:`Cloth`."""
    body = load_body(shape)
    seq = body_sequence or load_body_sequence(motion, body, max_frames=max_frames)
    cloth = outfit if isinstance(outfit, Cloth) else build_cloth(outfit, shape, edge_length)
    skinned = lbs(cloth.rest_vertices, cloth.skin_indices, cloth.skin_weights, seq.transforms)
    topology = model.make_topology(cloth) if model is not None else None
    name = outfit if isinstance(outfit, str) else "+".join(cloth.layer_names)
    return Scene(name, shape, seq.name or str(motion), cloth, seq, skinned, ClothRest.from_cloth(cloth), topology)


class SceneCache:
    """Bounded LRU cache of scenes keyed by (outfit, shape, motion)."""

    def __init__(self, model=None, edge_length: float = 0.035, capacity: int = 16) -> None:
        self.model = model
        self.edge_length = edge_length
        self.capacity = capacity
        self._scenes: OrderedDict[tuple[str, str, str], Scene] = OrderedDict()

    def get(self, outfit: str, shape: str, motion: str) -> Scene:
        key = (outfit, shape, motion)
        if key in self._scenes:
            self._scenes.move_to_end(key)
            return self._scenes[key]
        scene = make_scene(outfit, shape, motion, edge_length=self.edge_length, model=self.model)
        self._scenes[key] = scene
        while len(self._scenes) > self.capacity:
            self._scenes.popitem(last=False)
        return scene
