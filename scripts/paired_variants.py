"""Table 3's first inequality, paired per scene: one variant's figure minus another's on the same outfit × clip scenes.

    python scripts/paired_variants.py docs/results/r43_a_seen_full.json docs/results/r48_seen_no_repulsion_layer.json
    python scripts/paired_variants.py A.json B.json --a full --b no_repulsion_layer --key h_coll
    python scripts/paired_variants.py A1.json B1.json A2.json B2.json   # e.g. one pair per body shape, pooled

The files are ``smln eval --json`` outputs, in pairs (``A`` holds method ``--a``, ``B`` method ``--b``; one file may
hold both). Several pairs (the same scenes on another body shape, say) are pooled with their scenes kept apart.
Prints the frame-weighted figure of each, their paired difference A − B over the scenes both evaluated, its standard
error (:func:`shipping_rule.weighted_paired_difference`), how many scenes A is lower / higher on, and the same figures
per outfit; then the unweighted per-scene mean and its standard error (every scene alike, as
``scripts/shipping_rule.py`` prints its paired differences). The frame-weighted paired mean equals the difference of
the two frame-weighted means that ``smln eval`` prints when both evaluated the same scenes; the standard error says
whether that difference is larger than the scene-to-scene spread (docs/RESULTS.md, sessions 37-38).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from shipping_rule import load_runs, weighted_paired_difference  # noqa: E402

from smln.evaluate import RunResult, aggregate  # noqa: E402

SCALE = {"strain_mean": 100.0}  # fractions in the JSON, printed in %


def paired_variants(runs_a: list[RunResult], runs_b: list[RunResult], method_a: str, method_b: str,
                    key: str = "l_coll", weighted: bool = True) -> dict[str, dict[str, float]]:
    """Paired difference of ``key``, ``method_a`` − ``method_b``, over all scenes (``"all"``) and per outfit.

    ``weighted``: scenes weighted by their frames (the paired mean is then the difference of the frame-weighted
    means) or all alike (the per-scene mean that ``scripts/shipping_rule.py`` prints for information).

    Returns:
        per group (``"all"`` and each outfit both evaluated): ``a`` and ``b`` (frame-weighted means over the common
        scenes) and the fields of :func:`shipping_rule.weighted_paired_difference` (``mean``, ``se``, ``scenes``,
        ``better``: scenes where A is lower, ``worse``, ``unmatched``); empty when no scene is in both.
    """
    a = [r for r in runs_a if r.method == method_a]
    b = [dataclasses.replace(r, method=method_a) for r in runs_b if r.method == method_b]  # paired by scene
    scenes_a, scenes_b = {(r.outfit, r.motion) for r in a}, {(r.outfit, r.motion) for r in b}
    common, unmatched = scenes_a & scenes_b, float(len(scenes_a ^ scenes_b))
    out: dict[str, dict[str, float]] = {}
    if not common:
        return out
    for group in ["all"] + sorted({outfit for outfit, _ in common}):
        ga = [r for r in a if (r.outfit, r.motion) in common and group in ("all", r.outfit)]
        gb = [r for r in b if (r.outfit, r.motion) in common and group in ("all", r.outfit)]
        d = weighted_paired_difference(ga, gb, key, method=method_a, weighted=weighted)
        d["unmatched"] = unmatched  # scenes in only one of the two, over all outfits
        out[group] = {"a": aggregate(ga)[method_a][key], "b": aggregate(gb)[method_a][key], **d}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("evals", type=Path, nargs="+", metavar="A.json B.json",
                   help="smln eval --json outputs in pairs: one holding method --a, one holding method --b")
    p.add_argument("--a", default="full", help="method of the first file (default: full)")
    p.add_argument("--b", default="no_repulsion_layer", help="method of the second file (default: no_repulsion_layer)")
    p.add_argument("--key", default="l_coll", help="figure: l_coll, h_coll, strain_mean, ... (default: l_coll)")
    args = p.parse_args(argv)
    if len(args.evals) % 2:
        p.error("give the evaluations in pairs: A.json B.json [A2.json B2.json ...]")
    runs_a, runs_b = [], []
    for i, (file_a, file_b) in enumerate(zip(args.evals[::2], args.evals[1::2], strict=True)):
        tag = (lambda r: r) if len(args.evals) == 2 else (  # several pairs: the same clip of pair i is its own scene
            lambda r, i=i: dataclasses.replace(r, motion=f"{r.motion} [{i + 1}]"))
        runs_a += [tag(r) for r in load_runs([file_a])]
        runs_b += [tag(r) for r in load_runs([file_b])]
    rows = paired_variants(runs_a, runs_b, args.a, args.b, args.key)
    if not rows:
        raise SystemExit(f"no common scenes of {args.a} and {args.b} in {' '.join(map(str, args.evals))}")
    s = SCALE.get(args.key, 1.0)
    for group, d in rows.items():
        print(f"{group}: {args.key} {args.a} {d['a'] * s:.3f} - {args.b} {d['b'] * s:.3f} = {d['mean'] * s:+.3f} ± "
              f"{d['se'] * s:.3f} (SE) over {int(d['scenes'])} scenes, {args.a} lower on {int(d['better'])}, "
              f"higher on {int(d['worse'])}")
    d = paired_variants(runs_a, runs_b, args.a, args.b, args.key, weighted=False)["all"]
    print(f"per scene, unweighted: {d['mean'] * s:+.3f} ± {d['se'] * s:.3f} (SE)")
    if rows["all"]["unmatched"]:
        print(f"({int(rows['all']['unmatched'])} scenes evaluated in only one of the two files are left out)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
