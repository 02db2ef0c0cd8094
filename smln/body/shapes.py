"""Body-shape presets: anny phenotype sliders in [0, 1].

anny's anchors (``anny.models.model_data``): gender 0 = male, 1 = female; age interpolates newborn (-1/3), baby (0),
child (1/3), young adult (2/3), old (1), so adults sit at age >= 2/3. The other sliders stay within 0.3-0.7.
"""

from __future__ import annotations

BODY_SHAPES: dict[str, dict[str, float]] = {
    "female_average": {"gender": 1.0, "age": 0.7, "muscle": 0.5, "weight": 0.5, "height": 0.5, "proportions": 0.5},
    "male_average": {"gender": 0.0, "age": 0.7, "muscle": 0.5, "weight": 0.5, "height": 0.35, "proportions": 0.5},
    "tall_heavy": {"gender": 0.2, "age": 0.75, "muscle": 0.5, "weight": 0.7, "height": 0.5, "proportions": 0.5},
    "petite_slim": {"gender": 0.8, "age": 0.7, "muscle": 0.4, "weight": 0.35, "height": 0.3, "proportions": 0.5},
}
"""Preset name -> anny phenotype parameters."""

DEFAULT_SHAPE = "female_average"


def check_shape(name: str) -> str:
    """Return ``name`` if it is a known preset, else raise ``ValueError`` listing the presets."""
    if name not in BODY_SHAPES:
        raise ValueError(f"unknown body shape {name!r}; choose one of: {', '.join(BODY_SHAPES)}")
    return name
