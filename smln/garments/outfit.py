"""Outfits: ordered stacks of garment layers (inner -> outer), their registry and seen/unseen split.

Each layer is built with a body gap at least ``LAYER_GAP`` larger than the layer beneath, then pushed outward
wherever it is closer than ``LAYER_CLEARANCE`` to the layers beneath (nearest vertex, along its normal, the same
test as the L-Coll metric), so that at rest nothing penetrates (H-Coll = L-Coll = 0).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from smln.body import load_body
from smln.cloth import Cloth, Material
from smln.garments.garment import Garment, GarmentError
from smln.garments.generators import SPECS
from smln.garments.library import DEFAULT_EDGE_LENGTH, build_garment
from smln.garments.meshops import laplacian_smooth, push_out, signed_gap, vertex_normals_np

MANIFEST = Path(__file__).resolve().parent.parent / "data" / "outfits.json"
LAYER_GAP = 0.008
"""Extra body gap of each layer over the one beneath, m."""
LAYER_CLEARANCE = 0.004
"""Smallest rest distance of a layer in front of the layer beneath (nearest-vertex normal plane), m."""
BODY_CLEARANCE = 0.003
"""Smallest rest distance of any garment vertex in front of the body, m."""


@lru_cache(maxsize=1)
def _manifest() -> dict:
    return json.loads(MANIFEST.read_text())


def outfit_registry() -> dict[str, dict]:
    """Outfit name -> {"layers": [garment types inner -> outer], "split": "train" | "test_seen" | "test_unseen"}."""
    return dict(_manifest()["outfits"])


OUTFITS: dict[str, list[str]] = {k: list(v["layers"]) for k, v in outfit_registry().items()}
"""Outfit name -> garment types, inner -> outer."""


def outfit_split(name: str) -> str:
    """``"train"``, ``"test_seen"`` or ``"test_unseen"``."""
    _check(name)
    return outfit_registry()[name]["split"]


def training_outfits() -> list[str]:
    """Outfits training may use."""
    return [k for k, v in outfit_registry().items() if v["split"] == "train"]


def held_out_outfits() -> list[str]:
    """Outfits held out for evaluation (seen and unseen garment types)."""
    return [k for k, v in outfit_registry().items() if v["split"] != "train"]


def _check(name: str) -> None:
    if name not in OUTFITS:
        raise GarmentError(f"unknown outfit {name!r}; choose one of: {', '.join(OUTFITS)}")


def _normals(g: Garment) -> np.ndarray:
    return vertex_normals_np(g.vertices.astype(np.float64), g.faces)


@dataclass
class Outfit:
    """An ordered stack of garments, inner -> outer.

    Attributes:
        name: outfit name; layers: garments, layer 0 touches the body; shape: body shape preset.
        material: fabric constants of the :class:`~smln.cloth.Cloth` (shared by all layers).
    """

    name: str
    layers: list[Garment]
    shape: str = "female_average"
    material: Material = field(default_factory=Material)

    @property
    def num_vertices(self) -> int:
        return sum(g.num_vertices for g in self.layers)

    def to_cloth(self) -> Cloth:
        """Concatenate the layers into a :class:`~smln.cloth.Cloth` (layer 0 first; faces re-indexed)."""
        if not self.layers:
            raise GarmentError(f"outfit {self.name!r} has no layers")
        offsets = np.cumsum([0] + [g.num_vertices for g in self.layers])
        return Cloth(
            rest_vertices=torch.from_numpy(np.concatenate([g.vertices for g in self.layers]).astype(np.float32)),
            faces=torch.from_numpy(np.concatenate([g.faces + o for g, o in zip(self.layers, offsets, strict=False)])),
            layer_index=torch.from_numpy(np.repeat(np.arange(len(self.layers)), np.diff(offsets)).astype(np.int64)),
            vertex_mass=torch.from_numpy(np.concatenate([g.vertex_mass for g in self.layers]).astype(np.float32)),
            pinned=torch.from_numpy(np.concatenate([g.pinned for g in self.layers]).astype(bool)),
            skin_indices=torch.from_numpy(np.concatenate([g.skin_indices for g in self.layers]).astype(np.int64)),
            skin_weights=torch.from_numpy(np.concatenate([g.skin_weights for g in self.layers]).astype(np.float32)),
            material=self.material,
            layer_names=[g.name for g in self.layers],
        )

    def body_gaps(self) -> list[np.ndarray]:
        """Per layer, (V,) signed distance of each vertex in front of the nearest body vertex's normal plane, m."""
        body = load_body(self.shape)
        bv = body.rest_vertices.numpy().astype(np.float64)
        bn = vertex_normals_np(bv, body.faces.numpy())
        return [signed_gap(g.vertices.astype(np.float64), bv, bn) for g in self.layers]

    def layer_gaps(self) -> list[np.ndarray]:
        """Per layer k >= 1, (V_k,) signed distance in front of the nearest vertex of layer k - 1, m."""
        return [
            signed_gap(outer.vertices.astype(np.float64), inner.vertices.astype(np.float64), _normals(inner))
            for inner, outer in zip(self.layers[:-1], self.layers[1:], strict=True)
        ]

    def with_layer(self, garment: Garment, index: int | None = None) -> Outfit:
        """A new outfit with ``garment`` inserted (see :func:`smln.garments.obj_import.place_layer`)."""
        from smln.garments.obj_import import place_layer

        return place_layer(self, garment, index)


def _push_all(x: np.ndarray, under: list[tuple[np.ndarray, np.ndarray, float]]) -> np.ndarray:
    """Push points out of each (vertices, normals, clearance) surface in turn."""
    for v, n, clearance in under:
        x = push_out(x, v, n, clearance)
    return x


def settle_layers(layers: list[Garment], shape: str) -> list[Garment]:
    """Push each layer out of the body and of every layer beneath it (rest state without penetration)."""
    body = load_body(shape)
    bv = body.rest_vertices.numpy().astype(np.float64)
    bn = vertex_normals_np(bv, body.faces.numpy())
    out: list[Garment] = []
    for g in layers:
        x = push_out(g.vertices.astype(np.float64), bv, bn, BODY_CLEARANCE)
        if out:
            inner_v = np.concatenate([h.vertices.astype(np.float64) for h in out])
            inner_n = np.concatenate([_normals(h) for h in out])
            adj_v, adj_n = out[-1].vertices.astype(np.float64), _normals(out[-1])
            under = [(adj_v, adj_n, LAYER_CLEARANCE), (inner_v, inner_n, LAYER_CLEARANCE), (bv, bn, BODY_CLEARANCE)]

            # spread the push-out displacement over the mesh (a soft bulge instead of single-vertex ruffles),
            # then finish with the exact per-vertex push
            for _ in range(4):
                d = _push_all(x, under) - x
                if not d.any():
                    break
                x = x + 1.3 * laplacian_smooth(d, g.faces, iterations=8, alpha=0.5, taubin=False)
            for _ in range(12):
                y = _push_all(x, under)
                if np.array_equal(y, x):
                    break
                x = y
        out.append(g.with_vertices(x) if not np.array_equal(x, g.vertices) else g)
    return out


def build_outfit(name: str, shape: str = "female_average", edge_length: float = DEFAULT_EDGE_LENGTH) -> Outfit:
    """Build a registered outfit on body ``shape`` with target edge length ``edge_length`` (m).

    Layer k gets the body gap max(own default, gap of layer k-1 + :data:`LAYER_GAP`); then
    :func:`settle_layers` removes any remaining contact.
    """
    _check(name)
    layers, gap = [], 0.0
    for i, t in enumerate(OUTFITS[name]):
        offset = SPECS[t].offset if i == 0 else max(SPECS[t].offset, gap + LAYER_GAP)
        layers.append(build_garment(t, shape, edge_length, offset))
        gap = offset
    return Outfit(name, settle_layers(layers, shape), shape)
