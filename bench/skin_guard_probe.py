"""Which excursions past the rollout's skinned-distance bound are tangles? Rollouts without any guard.

Runs a checkpoint on outfits x clips with the distance bounds off (non-finite positions and the max-strain bound
still fall back), and per frame records the largest distance of a garment vertex from its skinned place and from
the body, H-Coll, L-Coll and the mean / max edge strain. Then it cuts each scene into *excursions* (consecutive
frames with a vertex more than ``--bound`` from its skinned place) and says which of them show a symptom of a
tangle under the rules of ``skin_guard="symptomatic"`` (:data:`smln.rollout.SKIN_GUARDS`): mean strain above
:data:`~smln.rollout.SYMPTOM_STRAIN_MEAN`, H-Coll above :data:`~smln.rollout.SYMPTOM_H_COLL`
(:func:`~smln.rollout.tangle_symptom`), a vertex beyond
:data:`~smln.rollout.HARD_SKIN_FACTOR` times the bound, or beyond :data:`~smln.rollout.MAX_BODY_DISTANCE` of the
body. Use training clips to design a guard, test clips to check it.

    python bench/skin_guard_probe.py [--checkpoint checkpoints/full] [--outfits tshirt_jacket ...]
        [--motions train] [--frames 150] [--out frames.json] [--summary excursions.json]
    python bench/skin_guard_probe.py --from-json frames.json      # the excursion table of an earlier run
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from smln.rollout import HARD_SKIN_FACTOR, MAX_BODY_DISTANCE, MAX_SKIN_DISTANCE, tangle_symptom

COLUMNS = ("frame", "skin_distance_max", "body_distance_max", "h_coll", "l_coll", "strain_mean", "strain_max")


def scene_frames(model, scene, num_frames: int) -> list[list[float]]:
    """Per frame the :data:`COLUMNS` of an unguarded rollout (distances m, H/L-Coll %, strain fractions)."""
    from smln.rollout import rollout

    n = min(num_frames, scene.num_frames - 2)
    skinned = np.asarray(scene.skinned)
    rows = []
    with torch.no_grad():
        for fr in rollout(model, scene.cloth, scene.body.slice(0, n + 1), scene.body.faces, num_frames=n,
                          fallback=True, max_distance=1e9, max_body_distance=1e9):
            skin = np.linalg.norm(fr.garment_positions - skinned[fr.index], axis=1).max()
            m = fr.metrics  # body_distance_max: the rollout's own nearest-body-vertex query of this frame
            rows.append([fr.index, float(skin), m["body_distance_max"], m["h_coll"], m["l_coll"], m["strain_mean"],
                         m["strain_max"]])
    return rows


def excursions(rows: list[list[float]], bound: float) -> list[dict]:
    """The runs of consecutive frames with ``skin_distance_max > bound``, each with its symptoms."""
    r = np.asarray(rows, dtype=float).reshape(-1, len(COLUMNS))
    frame, skin, body, h, _, strain, _ = r.T
    over = skin > bound
    symptom = over & (tangle_symptom(strain, h) | (skin > HARD_SKIN_FACTOR * bound) | (body > MAX_BODY_DISTANCE))
    out = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], over.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        before = slice(max(0, a - 10), a)
        out.append({
            "first_frame": int(frame[a]), "frames": int(b - a), "to_end": bool(b == len(over)),
            "symptom": bool(symptom[a:b].any()), "skin_distance_max": float(skin[a:b].max()),
            "body_distance_max": float(body[a:b].max()),
            "strain_mean_pct": 100 * float(strain[a:b].mean()),
            "strain_mean_before_pct": 100 * float(strain[before].mean()),
            "h_coll_pct": float(h[a:b].mean()), "h_coll_before_pct": float(h[before].mean()),
        })
    return out


def report(scenes: list[dict], bound: float) -> list[dict]:
    """Prints one line per excursion and the totals; returns the excursions with their scene."""
    table = []
    for s in scenes:
        for e in excursions(s["rows"], bound):
            table.append({"outfit": s["outfit"], "clip": s["clip"], **e})
            print(f"{s['outfit'][:24]:24s} {s['clip'][:30]:30s} frames {e['first_frame']:3d}+{e['frames']:3d}"
                  f"{' (to end)' if e['to_end'] else '         '} skin {e['skin_distance_max']:.2f} m, body "
                  f"{e['body_distance_max']:.2f} m, strain {e['strain_mean_pct']:.1f} % (before "
                  f"{e['strain_mean_before_pct']:.1f}), H-Coll {e['h_coll_pct']:.1f} % (before "
                  f"{e['h_coll_before_pct']:.1f}): {'SYMPTOM' if e['symptom'] else 'no symptom'}")
    n_sym = sum(e["symptom"] for e in table)
    print(f"{len(table)} excursions past {bound} m in {len(scenes)} scenes: {n_sym} with a symptom, "
          f"{len(table) - n_sym} without")
    return table


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default="checkpoints/full")
    p.add_argument("--outfits", nargs="+", default=["tshirt_jacket", "leggings_skirt", "tshirt_longsleeve_jacket"])
    p.add_argument("--motions", nargs="+", default=["train"], help="train | test | clip names")
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--bound", type=float, default=MAX_SKIN_DISTANCE, help="skinned-distance bound, m")
    p.add_argument("--out", help="write the per-frame rows as JSON")
    p.add_argument("--summary", help="write the excursion table as JSON")
    p.add_argument("--from-json", help="per-frame rows of an earlier --out: report only")
    a = p.parse_args()
    if a.from_json:
        scenes = json.loads(Path(a.from_json).read_text())
    else:
        from smln.checkpoint import load_checkpoint
        from smln.data_sampling import SceneCache
        from smln.evaluate import resolve_names
        from smln.geometry import set_threads

        set_threads(1)
        model, _ = load_checkpoint(a.checkpoint)
        cache = SceneCache(edge_length=0.035)
        scenes = []
        for outfit in a.outfits:
            for clip in resolve_names(a.motions, "motions"):
                rows = scene_frames(model, cache.get(outfit, "female_average", clip), a.frames)
                scenes.append({"outfit": outfit, "clip": clip, "columns": list(COLUMNS), "rows": rows})
                if a.out:
                    Path(a.out).write_text(json.dumps(scenes))
    table = report(scenes, a.bound)
    if a.summary:
        Path(a.summary).write_text(json.dumps({"checkpoint": a.checkpoint, "bound_m": a.bound, "excursions": table},
                                              indent=1))


if __name__ == "__main__":
    main()
