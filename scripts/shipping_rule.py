"""Apply the project's shipping rule to a candidate's test-clip evaluation (docs/RESULTS.md, sessions 12-15).

    python scripts/shipping_rule.py --seen OUTDIR/seen_*.json --held OUTDIR/held_*.json --sink-mm 44.1 \\
        [--shipped-seen docs/results/r22_seen_*.json] [--shipped-held docs/results/r22_held_*.json] [--max-sink-mm 34.5]

A candidate (the three variants, each evaluated by ``smln eval --json``) replaces the shipped checkpoints only if

1. no target figure of its full model is worse than the shipped full model's, on the seen and on the held-out
   outfits: L-Coll %, H-Coll %, mean edge strain and the number of fallback frames (raw values, not rounded);
2. the paper's Table 3 order holds on both splits: L-Coll(full) < L-Coll(no_repulsion_layer) < L-Coll(baseline);
3. the open jacket of tshirt_jacket sinks no more than ``--max-sink-mm`` (the shipped model's) below its
   skinned place at frame 50 of the walk (``bench/layer_sink.py``).

The defaults are the shipped model's since session 15 (r22: its evaluations and its 34.5 mm sink); sessions 12-15
judged against soup14 with ``--shipped-seen docs/results/soup14_seen.json --shipped-held
docs/results/soup14_unseen.json --max-sink-mm 122``. OUTDIR is the output of ``scripts/evaluate_candidate.sh``.

Prints one line per check and exits 0 when all pass, 1 otherwise. The figures are frame-weighted means over the
scenes, as ``smln eval`` prints them (:func:`smln.evaluate.aggregate`). After the verdict it prints, for information
only (the rule does not read it), the full model's paired per-scene differences (candidate − shipped on each outfit ×
clip both evaluated): their mean, its standard error and how many scenes are better or worse; a difference within
about two standard errors is of the size of the scene-to-scene changes.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from smln.evaluate import RunResult, aggregate, load_results

TARGETS = (("l_coll", "L-Coll %"), ("h_coll", "H-Coll %"), ("strain_mean", "strain mean %"),
           ("fallback_frames", "fallback frames"))
ORDER = ("full", "no_repulsion_layer", "baseline")


def load_runs(paths: list[Path]) -> list[RunResult]:
    """The runs of all ``smln eval --json`` outputs in ``paths``."""
    try:
        return load_results(paths)
    except ValueError as exc:  # unreadable, not eval output, or one run in two files
        raise SystemExit(f"cannot read evaluations: {exc}") from exc


def paired_differences(candidate: list[RunResult], shipped: list[RunResult], key: str,
                       method: str = "full") -> dict[str, float]:
    """Per-scene differences candidate − shipped of ``key`` for ``method`` on the outfit × clip pairs both have.

    Returns:
        ``scenes`` (count), ``mean`` (unweighted mean difference), ``se`` (its standard error, sample standard
        deviation / sqrt(scenes); NaN under two scenes), ``better`` / ``worse`` (scenes with a lower / higher value).
    """
    old = {(r.outfit, r.motion): r.metrics[key] for r in shipped if r.method == method}
    diffs = [r.metrics[key] - old[(r.outfit, r.motion)] for r in candidate
             if r.method == method and (r.outfit, r.motion) in old]
    n = len(diffs)
    mean = sum(diffs) / n if n else math.nan
    se = math.sqrt(sum((d - mean) ** 2 for d in diffs) / (n - 1) / n) if n > 1 else math.nan
    return {"scenes": float(n), "mean": mean, "se": se, "better": float(sum(d < 0 for d in diffs)),
            "worse": float(sum(d > 0 for d in diffs))}


def check(candidate: dict[str, dict[str, float]], shipped: dict[str, dict[str, float]],
          split: str) -> list[tuple[str, bool]]:
    """(description, passed) for rule 1 and rule 2 on one split."""
    out = []
    for method in ORDER:
        if method not in candidate:
            out.append((f"{split}: {method} evaluated", False))
    if "full" not in candidate or "full" not in shipped:
        return out
    for key, name in TARGETS:
        new, old = candidate["full"][key], shipped["full"][key]
        scale = 100.0 if key == "strain_mean" else 1.0  # a fraction in the JSON, printed in %
        out.append((f"{split}: full {name} {new * scale:.4g} <= shipped {old * scale:.4g}", new <= old))
    if all(m in candidate for m in ORDER):
        values = [candidate[m]["l_coll"] for m in ORDER]
        text = " < ".join(f"{m} {v:.3f}" for m, v in zip(ORDER, values, strict=True))
        out.append((f"{split}: L-Coll order {text}", values[0] < values[1] < values[2]))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seen", type=Path, nargs="+", required=True, help="candidate evaluations, seen outfits")
    p.add_argument("--held", type=Path, nargs="+", required=True, help="candidate evaluations, held-out outfits")
    shipped = [f"docs/results/r22_{{}}_{v}.json" for v in ORDER]  # the shipped model's evaluations, per variant
    p.add_argument("--shipped-seen", type=Path, nargs="+", default=[Path(f.format("seen")) for f in shipped])
    p.add_argument("--shipped-held", type=Path, nargs="+", default=[Path(f.format("held")) for f in shipped])
    p.add_argument("--sink-mm", type=float, required=True, help="candidate's jacket sink at frame 50, mm")
    p.add_argument("--max-sink-mm", type=float, default=34.5)
    a = p.parse_args(argv)
    runs = {split: (load_runs(new), load_runs(old))
            for split, new, old in (("seen", a.seen, a.shipped_seen), ("held-out", a.held, a.shipped_held))}
    checks = [c for split, (new, old) in runs.items() for c in check(aggregate(new), aggregate(old), split)]
    checks.append((f"sink at frame 50 {a.sink_mm:.1f} mm <= {a.max_sink_mm:.1f} mm", a.sink_mm <= a.max_sink_mm))
    for text, ok in checks:
        print(f"{'pass' if ok else 'FAIL'}  {text}")
    passed = all(ok for _, ok in checks)
    print("ship" if passed else "do not ship")
    print("paired per-scene differences of the full model, candidate - shipped (information, not the rule):")
    for split, (new, old) in runs.items():
        for key, name in TARGETS[:3]:
            d = paired_differences(new, old, key)
            scale = 100.0 if key == "strain_mean" else 1.0
            print(f"  {split}: {name} {d['mean'] * scale:+.3f} ± {d['se'] * scale:.3f} (SE) over {int(d['scenes'])} "
                  f"scenes, {int(d['better'])} better, {int(d['worse'])} worse")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
