"""Checkpoint selection on training scenes: pick one of a run's snapshots by rollouts on several outfits and clips.

The trainer keeps its ``best`` by one 120-frame validation rollout (one outfit, one clip). Sessions 16-18 found that
clip a poor predictor of the test clips at the level the checkpoints have reached (docs/RESULTS.md, r24 and r25).
``smln select`` scores every checkpoint given on a fixed set of *training* outfits and clips (the test clips and
held-out outfits are refused, so a selection never sees the test split) and ranks them by the trainer's validation
score::

    smln select runs/r26_full/snapshots/*.json runs/r26_full/best --json runs/r26_full/selection.json

The score (lower is better) is :func:`selection_score`: mean edge strain (a fraction) + H-Coll / 100 + L-Coll / 100
+ the fraction of frames that fell back to skinning, i.e. :meth:`smln.train.Trainer.validate`'s with the
fallbacks counted per frame instead of as one explosion.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from smln.evaluate import RunResult, aggregate, evaluate

SELECTION_OUTFITS = ("tshirt_jacket", "leggings_skirt", "tshirt_longsleeve_jacket", "tanktop_tshirt")
"""Training outfits scored by default: the three seen test outfits and one with a tank top (session 13 saw the
held-out L-Coll rise on the tank-top outfits first)."""
SELECTION_MOTIONS = ("06_10_dribble_left_turns", "02_09_swordplay", "08_07_walk_exaggerated_stride")
"""Training clips scored by default: a dribble with turns, an action clip with wide arm swings, a walk."""


def selection_score(row: dict[str, float]) -> float:
    """The score of one checkpoint's :func:`smln.evaluate.aggregate` row (lower is better).

    Args:
        row: ``strain_mean`` (fraction), ``h_coll`` and ``l_coll`` (%), ``fallback_frames`` and ``frames`` (counts).

    Returns:
        strain_mean + h_coll / 100 + l_coll / 100 + fallback_frames / frames; ``inf`` when any of them is not finite
        (a rollout that produced NaN metrics is never selected).
    """
    frames = max(float(row["frames"]), 1.0)
    score = (float(row["strain_mean"]) + float(row["h_coll"]) / 100.0 + float(row["l_coll"]) / 100.0
             + float(row["fallback_frames"]) / frames)
    return score if math.isfinite(score) else math.inf


def rank(results: list[RunResult]) -> list[dict]:
    """The checkpoints of ``results`` (one method per checkpoint) ranked by :func:`selection_score`, best first.

    Returns:
        One dict per method: ``checkpoint`` (the method name), ``score`` and the aggregated metrics
        (:func:`smln.evaluate.aggregate`, frame-weighted over the scenes). Ties keep the order of first appearance.
    """
    rows = aggregate(results)
    ranked = [{"checkpoint": name, "score": selection_score(row), **row} for name, row in rows.items()]
    return sorted(ranked, key=lambda r: r["score"])  # sorted() is stable


def check_training_split(outfits: list[str], motions: list[str]) -> None:
    """Refuse a selection that would look at the test split.

    Raises:
        ValueError: naming the first held-out outfit or test clip given.
    """
    from smln.data_sampling import outfit_names
    from smln.motion import list_clips

    train_outfits, train_motions = set(outfit_names("train")), set(list_clips("train"))
    for outfit in outfits:
        if outfit not in train_outfits:
            raise ValueError(f"{outfit!r} is not a training outfit: selection scores the training split only "
                             f"({', '.join(sorted(train_outfits))})")
    for motion in motions:
        if motion not in train_motions:
            raise ValueError(f"{motion!r} is not a training clip: selection scores the training split only "
                             "(see `smln motions`)")


def cli_main(args: argparse.Namespace) -> None:
    main(args.argv)


def main(argv: list[str] | None = None) -> list[dict]:
    from smln.body import DEFAULT_SHAPE
    from smln.checkpoint import load_checkpoint
    from smln.geometry import set_threads

    p = argparse.ArgumentParser(prog="smln select", description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+", help="checkpoints to score (e.g. a run's snapshots/*.json, best, last)")
    p.add_argument("--outfits", nargs="+", default=list(SELECTION_OUTFITS), help="training outfits")
    p.add_argument("--motions", nargs="+", default=list(SELECTION_MOTIONS), help="training clips")
    p.add_argument("--frames", type=int, default=80, help="frames per clip (default %(default)s)")
    p.add_argument("--shape", default=DEFAULT_SHAPE,
                   help="body shape preset: female_average, male_average, tall_heavy or petite_slim "
                        "(default: %(default)s)")
    p.add_argument("--edge-length", type=float, default=0.035, help="garment resolution, m (default: training's)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", help="write the ranking (and the command's settings) to this file")
    a = p.parse_args(argv)
    if a.frames < 3:
        raise ValueError(f"--frames must be at least 3 (two skinned frames and one prediction), got {a.frames}")
    check_training_split(a.outfits, a.motions)
    names = [str(Path(c)) for c in a.checkpoints]
    if len(set(names)) != len(names):
        raise ValueError("a checkpoint is given twice")
    set_threads(a.threads)
    models = {name: load_checkpoint(name)[0] for name in names}
    results = evaluate(models, a.outfits, a.motions, shape=a.shape, frames=a.frames, edge_length=a.edge_length)
    ranked = rank(results)
    print(f"{'checkpoint':60s} {'score':>8s} {'strain %':>8s} {'H-Coll %':>8s} {'L-Coll %':>8s} {'fallback':>8s}")
    for r in ranked:
        print(f"{r['checkpoint']:60s} {r['score']:8.5f} {100 * r['strain_mean']:8.3f} {r['h_coll']:8.3f} "
              f"{r['l_coll']:8.3f} {int(r['fallback_frames']):8d}")
    if a.json:
        settings = {"outfits": a.outfits, "motions": a.motions, "frames": a.frames, "shape": a.shape,
                    "edge_length": a.edge_length}
        Path(a.json).write_text(json.dumps({"settings": settings, "ranking": ranked}, indent=1))
    return ranked
