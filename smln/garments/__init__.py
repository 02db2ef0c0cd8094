"""Garments and outfits generated on the anny body (see docs/ARCHITECTURE.md, "Garments").

Public API::

    from smln.garments import build_outfit, OUTFITS, Outfit, Garment, GarmentError, build_garment
    cloth = build_outfit("tshirt_jacket", shape="female_average", edge_length=0.02).to_cloth()
"""

from smln.garments.garment import Garment, GarmentError, vertex_mass
from smln.garments.generators import SPECS, GarmentSpec
from smln.garments.library import (
    DEFAULT_EDGE_LENGTH,
    GARMENT_TYPES,
    TRAINING_EDGE_LENGTH,
    build_garment,
    cache_dir,
)
from smln.garments.outfit import (
    OUTFITS,
    Outfit,
    build_outfit,
    held_out_outfits,
    outfit_registry,
    outfit_split,
    training_outfits,
)

__all__ = [
    "DEFAULT_EDGE_LENGTH",
    "GARMENT_TYPES",
    "OUTFITS",
    "SPECS",
    "TRAINING_EDGE_LENGTH",
    "Garment",
    "GarmentError",
    "GarmentSpec",
    "Outfit",
    "build_garment",
    "build_outfit",
    "cache_dir",
    "held_out_outfits",
    "outfit_registry",
    "outfit_split",
    "training_outfits",
    "vertex_mass",
]
