"""Write the outfit pictures in ``docs/outfits/`` and ``docs/outfits.png`` (``python -m smln.garments.figures``)."""

from __future__ import annotations

from pathlib import Path

from smln.garments.outfit import OUTFITS, build_outfit
from smln.garments.render import render_outfit, render_overview

DOCS = Path(__file__).resolve().parents[2] / "docs"


def write_figures(shape: str = "female_average") -> list[Path]:
    """Render every registered outfit (front, side, back) and an overview grid; returns the paths."""
    outfits = [build_outfit(n, shape) for n in OUTFITS]
    paths = [render_outfit(o, DOCS / "outfits" / f"{o.name}.png") for o in outfits]
    paths.append(render_overview(outfits, DOCS / "outfits.png"))
    return paths


if __name__ == "__main__":
    for p in write_figures():
        print(p)
