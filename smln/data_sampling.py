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
    """Scenes for training, built from separately cached parts.

    The outfit parts (cloth, rest state, graph topology) are cached per (outfit, shape) without limit (a few dozen
    small objects); posed body sequences per (shape, clip) in a bounded LRU (tens of MB each). Assembling a scene
    from cached parts costs one skinning of the garments along the clip. Every tensor of a scene (cloth, rest
    state, topology, body, skinned garments) lives on ``device`` (a GPU run keeps them there for the whole run).
    """

    def __init__(self, model=None, edge_length: float = 0.035, capacity: int = 48,
                 device: torch.device | str = "cpu") -> None:
        self.model = model
        self.edge_length = edge_length
        self.capacity = capacity
        self.device = torch.device(device)
        self._outfits: dict[tuple[str, str], tuple[Cloth, ClothRest, object | None]] = {}
        self._bodies: OrderedDict[tuple[str, str], BodySequence] = OrderedDict()

    def outfit(self, outfit: str, shape: str) -> tuple[Cloth, ClothRest, object | None]:
        key = (outfit, shape)
        if key not in self._outfits:
            cloth = build_cloth(outfit, shape, self.edge_length)
            rest = ClothRest.from_cloth(cloth).to(self.device)  # computed on the CPU: the same numbers everywhere
            cloth = cloth.to(self.device)
            topo = self.model.make_topology(cloth) if self.model is not None else None
            self._outfits[key] = (cloth, rest, topo)
        return self._outfits[key]

    def body(self, shape: str, motion: str) -> BodySequence:
        key = (shape, motion)
        if key in self._bodies:
            self._bodies.move_to_end(key)
            return self._bodies[key]
        seq = load_body_sequence(motion, load_body(shape)).to(self.device)
        self._bodies[key] = seq
        while len(self._bodies) > self.capacity:
            self._bodies.popitem(last=False)
        return seq

    def get(self, outfit: str, shape: str, motion: str, window: tuple[int, int] | None = None) -> Scene:
        """The scene; with ``window=(start, stop)`` only frames start:stop of the clip (skinning is the cost)."""
        cloth, rest, topo = self.outfit(outfit, shape)
        seq = self.body(shape, motion)
        if window is not None:
            seq = seq.slice(*window)
        skinned = lbs(cloth.rest_vertices, cloth.skin_indices, cloth.skin_weights, seq.transforms)
        return Scene(outfit, shape, motion, cloth, seq, skinned, rest, topo)
