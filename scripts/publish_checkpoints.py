"""Copy trained runs into ``checkpoints/<variant>/`` with their model cards (JSON + markdown).

    python scripts/publish_checkpoints.py --runs runs --which best [--eval-json results.json] \
        [--pick full=snapshots/step_0286037 ...]

For each variant (full, no_repulsion_layer, baseline) it copies ``runs/<variant>/<which>.safetensors`` (``--pick
VARIANT=WHICH`` names another checkpoint of that variant's run, e.g. a snapshot ``smln select`` chose) to
``checkpoints/<variant>/model.safetensors``, writes ``card.json`` (the training card, plus the evaluation figures
of that variant when ``--eval-json`` from ``smln eval --json`` is given) and a short ``README.md`` model card.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

DESCRIPTIONS = {
    "full": "repulsion layer + repulsion loss (the paper's full model, Table 3 last row)",
    "no_repulsion_layer": "repulsion loss only, no repulsion layer (Table 3 'W/o repulsion')",
    "baseline": "neither repulsion layer nor repulsion loss (Table 3 'W/o loss and repulsion')",
}
BODY_STAGE_NOTE = ("; the repulsion layer also has a body stage, our extension of the paper: the same learned push "
                   "between the body and the garments, before the layer pairs (SMLNConfig.body_repulsion)")


def eval_summary(results: list[dict], method: str) -> dict[str, float]:
    rows = [r for r in results if r["method"] == method]
    if not rows:
        return {}
    w = np.array([r["metrics"]["num_frames"] for r in rows])
    keys = ("l_coll", "h_coll", "bend", "collision_loss", "strain_mean", "ms_model")
    out = {k: float(np.average([r["metrics"][k] for r in rows], weights=w)) for k in keys}
    out["strain_max"] = float(max(r["metrics"]["strain_max_max"] for r in rows))
    out["fallback_frames"] = float(sum(r["metrics"].get("fallback_frames", 0) for r in rows))
    out["frames"] = float(w.sum())
    out["outfits"] = sorted({r["outfit"] for r in rows})
    out["motions"] = sorted({r["motion"] for r in rows})
    return out


def constant_body_push(checkpoint: Path) -> float | None:
    """The body stage's push fraction when it does not depend on its input (its MLP's last layer all zero, as
    ``--freeze-body-stage`` keeps it from ``init_as_projection``, and as the average of such runs stays), else None."""
    import torch

    from smln.checkpoint import load_checkpoint

    model, _ = load_checkpoint(checkpoint)
    last = model.body_repulsion.mlp[-1]
    if bool(last.weight.detach().eq(0).all()):
        return float(torch.nn.functional.softplus(last.bias.detach()).item())
    return None


def publish(run_dir: Path, variant: str, which: str, dest: Path, results: list[dict] | None) -> Path:
    from smln.checkpoint import load_checkpoint

    src_card = run_dir / f"{which}.json"
    card = json.loads(src_card.read_text())
    init = card.get("training", {}).get("init_from")
    if init and "initialised_from" not in card and (Path(init) / "card.json").is_file():
        # runs started before the trainer recorded its parent: take it from the parent card (read before the
        # parent is overwritten below when it is the published checkpoint itself)
        parent = json.loads((Path(init) / "card.json").read_text())
        if parent.get("sha256") == card.get("sha256"):  # republishing: that card is this run's, lineage included
            card["initialised_from"] = parent.get("initialised_from")
        else:
            tr0 = parent.get("training", {})
            card["initialised_from"] = {"path": init, "steps": tr0.get("steps"),
                                        "wall_time_s": tr0.get("wall_time_s"), "hardware": tr0.get("hardware"),
                                        "initialised_from": parent.get("initialised_from")}
    entry = card.get("initialised_from")
    if entry and "loss_weights" not in entry and (Path(entry.get("path", "")) / "card.json").is_file():
        # runs started before the trainer recorded the parent's loss weights: read them from the parent card, or,
        # when republishing (the parent path holds this very checkpoint), keep the lineage already published
        parent = json.loads((Path(entry["path"]) / "card.json").read_text())
        if parent.get("sha256") != card.get("sha256"):
            entry["loss_weights"] = parent.get("loss_weights")
        elif parent.get("initialised_from"):
            card["initialised_from"] = parent["initialised_from"]
    out = dest / variant
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(run_dir / f"{which}.safetensors", out / "model.safetensors")
    card["tensors_file"] = "model.safetensors"
    card["description"] = DESCRIPTIONS[variant] + (BODY_STAGE_NOTE if card["config"].get("body_repulsion") else "")
    push = constant_body_push(run_dir / which) if card["config"].get("body_repulsion") else None
    if push is not None:
        card["description"] += (f"; its body stage was not trained (smln train --freeze-body-stage): it pushes every "
                                f"vertex it acts on {push:.2f} of the way to its threshold")
    if results:
        card["evaluation"] = eval_summary(results, variant)
    (out / "card.json").write_text(json.dumps(card, indent=2, sort_keys=True))
    load_checkpoint(out)  # validates what was written
    tr = card.get("training", {})
    ev = card.get("evaluation", {})
    md = [
        f"# SMLN checkpoint `{variant}`",
        "",
        f"{card['description']}.",
        "",
        "Trained self-supervised (physics losses only, no garment data) on the training split of outfits and CMU",
        "clips; see `docs/RESULTS.md` for the tables and `card.json` for every setting.",
        "",
        f"- steps: {tr.get('steps')}, wall time: {tr.get('wall_time_s')} s, processes: {tr.get('processes')}, "
        f"device: {tr.get('device')}",
        f"- hardware: {tr.get('hardware')}, torch {tr.get('torch')}",
        f"- architecture: {json.dumps(card.get('config'))}",
        f"- loss weights: {json.dumps(card.get('loss_weights'))}",
    ]
    if card.get("averaged_from"):  # a weight average (`smln average`) of runs fine-tuned from one parent
        parts = []
        for a in card["averaged_from"]:
            tr_a = a.get("training") or {}
            parts.append(f"{a.get('path')} (weight {a.get('weight'):.2f}, {a.get('steps')} steps, "
                         f"{tr_a.get('wall_time_s')} s, input noise {tr_a.get('noise_std')} m "
                         f"{tr_a.get('noise_mode', 'isotropic')})")
        md.append("- parameters averaged (`smln average`) from: " + "; ".join(parts)
                  + " (steps: the largest input's; wall time: the sum)")
    lineage, parent = [], card.get("initialised_from")
    while parent:  # fine-tuned runs: the runs they continued, newest first
        rep = (parent.get("loss_weights") or {}).get("repulsion")
        lineage.append(f"{parent.get('steps')} steps / {parent.get('wall_time_s')} s ({parent.get('hardware')}"
                       + (f", repulsion weight {rep:g}" if rep is not None else "") + ")")
        parent = parent.get("initialised_from")
    if lineage:
        md.append("- continued from earlier training: " + "; then from ".join(lineage)
                  + " (steps count from the start of the first run; wall time above is this run's only)")
    if "validation" in card:
        md.append(f"- validation rollout at selection: {json.dumps(card['validation'])}")
    if ev:
        md += [
            "",
            "## Evaluation (test clips, never seen in training)",
            "",
            f"outfits: {', '.join(ev['outfits'])}; clips: {', '.join(ev['motions'])}; {int(ev['frames'])} frames",
            "",
            "| L-Coll % | H-Coll % | Bend | Collision loss (mm²) | strain mean % | strain max % | ms/frame "
            "| fallback frames |",
            "|---|---|---|---|---|---|---|---|",
            f"| {ev['l_coll']:.2f} | {ev['h_coll']:.2f} | {ev['bend']:.4f} | {ev['collision_loss'] * 1e6:.3f} | "
            f"{100 * ev['strain_mean']:.2f} | {100 * ev['strain_max']:.1f} | {ev['ms_model']:.0f} | "
            f"{int(ev['fallback_frames'])} |",
        ]
    md += ["", f"Load it with `smln.checkpoint.load_checkpoint(\"{out.as_posix()}\")` (safetensors, no code "
           "is executed)."]
    dropped = hand_written_sections(out / "README.md", md)
    if dropped:
        print(f"{out / 'README.md'}: rewritten without its hand-written section(s) {', '.join(dropped)}; their old "
              "text is in git (git show HEAD:<path>): update them for this checkpoint and add them again",
              file=sys.stderr)
    (out / "README.md").write_text("\n".join(md) + "\n")
    return out


def hand_written_sections(readme: Path, generated: list[str]) -> list[str]:
    """The ``## `` headings of an existing model card that the generated card (``generated``, its lines) lacks:
    sections written by hand (e.g. "## Lineage and budget") that rewriting the card would drop."""
    if not readme.is_file():
        return []
    ours = {line for line in generated if line.startswith("## ")}
    return [line for line in readme.read_text().splitlines() if line.startswith("## ") and line not in ours]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", default="runs")
    p.add_argument("--which", default="best", help="best, last, or a snapshot: snapshots/step_NNNNNNN")
    p.add_argument("--pick", nargs="+", default=[], metavar="VARIANT=WHICH",
                   help="per-variant override of --which, e.g. baseline=snapshots/step_0285487")
    p.add_argument("--dest", default="checkpoints")
    p.add_argument("--eval-json", nargs="+", help="smln eval --json outputs (one or several, e.g. one per variant)")
    p.add_argument("--variants", nargs="+", default=list(DESCRIPTIONS))
    p.add_argument("--prefix", default="", help="run directories are RUNS/<prefix><variant> (e.g. ft_)")
    a = p.parse_args()
    results = [row for f in a.eval_json for row in json.loads(Path(f).read_text())] if a.eval_json else None
    picks = dict(item.split("=", 1) for item in a.pick if "=" in item)
    if len(picks) != len(a.pick) or not set(picks) <= set(a.variants):
        p.error(f"--pick takes VARIANT=WHICH with VARIANT one of {a.variants}; got {a.pick}")
    for v in a.variants:
        which = picks.get(v, a.which)
        if not (Path(a.runs) / f"{a.prefix}{v}" / f"{which}.safetensors").is_file():
            p.error(f"no checkpoint {which}.safetensors in {Path(a.runs) / f'{a.prefix}{v}'}")
        print(publish(Path(a.runs) / f"{a.prefix}{v}", v, which, Path(a.dest), results))


if __name__ == "__main__":
    main()
