"""Evaluation: roll checkpoints out over test clips and print the paper's tables.

``smln eval --checkpoint checkpoints/full --checkpoint checkpoints/baseline --outfits seen --motions test``
prints, per method, Bend, Collision loss, L-Coll %, H-Coll % (paper Tables 1/3), per unseen outfit (Table 2),
plus mean/max edge strain, ms/frame and the number of frames that fell back to skinning, with a skinning-only row
(garments rigidly skinned, no network) for reference.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from smln.body import DEFAULT_SHAPE, load_body
from smln.data_sampling import make_scene
from smln.geometry import set_threads
from smln.losses import ClothRest
from smln.metrics import frame_metrics, sequence_metrics
from smln.model.smln import BODY_PAIRINGS, REPULSION_PAIRINGS
from smln.rollout import MAX_BODY_DISTANCE, MAX_SKIN_DISTANCE, SKIN_GUARDS, RolloutFrame

TABLE_KEYS = ("bend", "collision_loss", "l_coll", "h_coll", "strain_mean", "strain_max", "offset_rms", "ms_model",
              "fallback", "l_coll_surface", "h_coll_surface")
SURFACE_KEYS = ("l_coll_surface", "h_coll_surface")
"""Point-to-triangle L-Coll / H-Coll (%), with ``--surface-metrics`` (:func:`smln.metrics.surface_l_coll`)."""


@dataclass
class RunResult:
    """Metrics of one method on one outfit × clip."""

    method: str
    outfit: str
    motion: str
    split: str
    metrics: dict[str, float]
    per_frame: list[dict[str, float]] = field(default_factory=list)


def skinning_frames(scene, num_frames: int) -> Iterator[RolloutFrame]:
    """The skinning-only reference: garments rigidly skinned onto the body, no dynamics."""
    rest = ClothRest.from_cloth(scene.cloth)
    faces = scene.body.faces.numpy()
    zeros = np.zeros((scene.cloth.num_vertices, 3), np.float32)
    for t in range(num_frames):
        t0 = time.perf_counter()
        x = scene.skinned[t]
        fm = frame_metrics(x, scene.body.vertices[t], rest, body_faces=faces)
        m = dict(fm.values)
        m["ms_model"] = 1e3 * (time.perf_counter() - t0)
        yield RolloutFrame(t, x.numpy(), scene.body.vertices[t].numpy(), zeros, zeros, fm.layer_penetration,
                           fm.body_penetration, m, False)


def method_frames(method: str, model, scene, num_frames: int, device: str = "cpu", project_body: bool = False,
                  project_layers: bool = False, precision: str = "float32", compiled: bool = False,
                  guards: dict[str, float | str] | None = None) -> Iterator[RolloutFrame]:
    """Frames of a method: ``skinning``, ``solver`` (reference L-BFGS) or a loaded model (optionally with the
    collision projection of :mod:`smln.projection` after each step, the processor in ``precision`` and compiled,
    :mod:`smln.model.compiled`; ``guards``: divergence bounds passed to :func:`smln.rollout.rollout`, e.g.
    ``{"max_distance": 0.4, "max_body_distance": 0.45}``)."""
    if method == "skinning":
        return skinning_frames(scene, num_frames)
    if method == "solver":
        from smln.solver import solver_rollout

        return solver_rollout(scene.cloth, scene.body, num_frames=num_frames)
    from smln.rollout import rollout

    return rollout(model, scene.cloth, scene.body, scene.body.faces, num_frames=num_frames, device=device,
                   fallback=True, project_body=project_body, project_layers=project_layers, precision=precision,
                   compiled=compiled, **(guards or {}))


def summarise(
    frames: Iterable[RolloutFrame], skinned: torch.Tensor | None = None, surface_scene=None,
    rest: ClothRest | None = None,
) -> tuple[dict[str, float], list[dict[str, float]]]:
    """Sequence metrics of a method's frames; with ``skinned`` (T, V, 3) also ``offset_rms``, the RMS distance
    (m) of the garment from its rigidly skinned position: how much it moves with its own dynamics; with a
    ``surface_scene`` (its cloth's faces and layers, its body's faces) also the point-to-triangle
    ``l_coll_surface`` / ``h_coll_surface`` (%, ~80 ms per frame on the 24k-face body); with ``rest`` (a
    multi-layer cloth's) also ``layer_slip`` (m per frame, :func:`smln.metrics.layer_slip`; NaN on a frame that
    or whose predecessor fell back to skinning, where the reset is no slip)."""
    from smln.metrics import layer_slip, surface_h_coll, surface_l_coll

    rows = []
    previous: RolloutFrame | None = None
    if surface_scene is not None:
        faces, layers = surface_scene.cloth.faces.numpy(), surface_scene.cloth.layer_index.numpy()
        body_faces = surface_scene.body.faces.numpy()
    for fr in frames:
        m = dict(fr.metrics)
        m["fallback"] = float(fr.fallback)
        if surface_scene is not None:
            m["l_coll_surface"] = surface_l_coll(fr.garment_positions, faces, layers)
            m["h_coll_surface"] = surface_h_coll(fr.garment_positions, fr.body_vertices, body_faces)
        if skinned is not None:
            d = fr.garment_positions - skinned[fr.index].numpy()
            m["offset_rms"] = float(np.sqrt((d**2).sum(-1).mean()))
        if rest is not None and rest.num_layers > 1:
            continuous = previous is not None and not (fr.fallback or previous.fallback)
            m["layer_slip"] = layer_slip(previous.garment_positions, fr.garment_positions, rest) if continuous \
                else float("nan")
        previous = fr
        rows.append(m)
    seq = sequence_metrics(rows)
    seq["fallback_frames"] = float(sum(r["fallback"] for r in rows))
    # ms/frame over the network frames only (frames 0-1 are the skinned initial state)
    ms = [r["ms_model"] for r in rows[2:]] or [0.0]
    seq["ms_model"] = float(np.median(ms))
    return seq, rows


def evaluate(
    methods: dict[str, object | None],
    outfits: list[str],
    motions: list[str],
    *,
    shape: str = DEFAULT_SHAPE,
    frames: int | None = None,
    edge_length: float = 0.02,
    device: str = "cpu",
    progress: bool = True,
    project_body: bool = False,
    project_layers: bool = False,
    precision: str = "float32",
    compiled: bool = False,
    surface_metrics: bool = False,
    guards: dict[str, float | str] | None = None,
) -> list[RunResult]:
    """Run every method on every outfit × clip.

    Args:
        methods: display name -> loaded model (or None for ``skinning``/``solver``).
        outfits, motions: names. shape: body preset. frames: frames per clip (None = full clip).
        project_body, project_layers: the models' rollouts use the collision projection (smln.projection).
        precision: the models' processor precision (smln.model.precision).
        compiled: the models' processor runs through torch.compile (smln.model.compiled).
        surface_metrics: also the point-to-triangle L-Coll / H-Coll (:data:`SURFACE_KEYS`).
        guards: the models' divergence bounds (:func:`method_frames`; None: the rollout's defaults).
    """
    from smln.garments import outfit_split
    from smln.motion import load_body_sequence

    body = load_body(shape)
    results = []
    for motion in motions:
        seq = load_body_sequence(motion, body, max_frames=frames)
        for outfit in outfits:
            scene = make_scene(outfit, shape, motion, edge_length=edge_length, body_sequence=seq)
            n = scene.num_frames
            rest = ClothRest.from_cloth(scene.cloth)  # for the layer slip of every method's frames
            for name, model in methods.items():
                t0 = time.time()
                kind = name if model is None else "model"
                frames_it = method_frames(kind, model, scene, n, device, project_body, project_layers, precision,
                                          compiled, guards)
                seq_metrics, rows = summarise(frames_it, scene.skinned, scene if surface_metrics else None, rest)
                if progress:
                    print(f"  {name:20s} {outfit:26s} {motion:36s} {n:4d} frames "
                          f"L-Coll {seq_metrics['l_coll']:.2f}% H-Coll {seq_metrics['h_coll']:.2f}% "
                          f"({time.time() - t0:.0f} s)", flush=True)
                results.append(RunResult(name, outfit, motion, outfit_split(outfit), seq_metrics, rows))
    return results


def aggregate(results: list[RunResult], key: str = "method") -> dict[str, dict[str, float]]:
    """Mean of each table metric per method (or per ``(method, outfit)`` with key='outfit'), frame-weighted."""
    groups: dict[str, list[RunResult]] = {}
    for r in results:
        g = r.method if key == "method" else f"{r.method} | {r.outfit}"
        groups.setdefault(g, []).append(r)
    out = {}
    for g, rs in groups.items():
        w = np.array([r.metrics["num_frames"] for r in rs])
        row = {k: float(np.average([r.metrics.get(k, np.nan) for r in rs], weights=w)) for k in TABLE_KEYS
               if k not in ("strain_max", "fallback")}
        slip = np.array([r.metrics.get("layer_slip", np.nan) for r in rs])
        ok = np.isfinite(slip)  # runs without a continuous multi-layer frame have none
        row["layer_slip"] = float(np.average(slip[ok], weights=w[ok])) if ok.any() else float("nan")
        row["strain_max"] = float(max(r.metrics.get("strain_max_max", np.nan) for r in rs))
        row["fallback_frames"] = float(sum(r.metrics.get("fallback_frames", 0) for r in rs))
        row["frames"] = float(w.sum())
        row["exploded_frames"] = float(sum(r.metrics.get("exploded", 0) * r.metrics["num_frames"] for r in rs))
        out[g] = row
    return out


def _cell(value: float) -> str:
    """A cell of an optional metric: two decimals, or an em dash where it was not measured (a method run
    without ``--surface-metrics``, a single-layer outfit's layer slip)."""
    return f"{value:.2f}" if np.isfinite(value) else "—"


def markdown_table(rows: dict[str, dict[str, float]], title: str) -> str:
    """Markdown table of :func:`aggregate` rows (keys ``method`` or ``method | outfit``)."""
    per_outfit = any(" | " in k for k in rows)
    surface = any(np.isfinite(r.get(k, np.nan)) for r in rows.values() for k in SURFACE_KEYS)
    first = "| method | outfit " if per_outfit else "| method "
    head = (first + "| Bend ↓ | Collision loss (mm²) ↓ | L-Coll % ↓ | H-Coll % ↓ "
            + ("| L-Coll surf. % ↓ | H-Coll surf. % ↓ " if surface else "")
            + "| strain mean % | strain max % | offset from skinning (cm RMS) | layer slip (mm/frame) | ms/frame "
            "| fallback frames | frames |")
    lines = [f"**{title}**", "", head, "|" + "---|" * ((13 if per_outfit else 12) + (2 if surface else 0))]
    for name, r in rows.items():
        extra = "".join(f"| {_cell(r.get(k, np.nan))} " for k in SURFACE_KEYS) if surface else ""
        lines.append(
            f"| {name} | {r['bend']:.4f} | {r['collision_loss'] * 1e6:.3f} | {r['l_coll']:.2f} | {r['h_coll']:.2f} "
            + extra
            + f"| {100 * r['strain_mean']:.2f} | {100 * r['strain_max']:.1f} | {100 * r['offset_rms']:.2f} "
            f"| {_cell(1e3 * r.get('layer_slip', np.nan))} | {r['ms_model']:.0f} "
            f"| {int(r['fallback_frames'])} | {int(r['frames'])} |"
        )
    return "\n".join(lines) + "\n"


def resolve_names(spec: list[str] | None, kind: str) -> list[str]:
    """Outfit or clip names from a split name (train/test, seen/unseen) or explicit names."""
    from smln.data_sampling import outfit_names
    from smln.motion import list_clips

    if not spec:
        spec = ["seen"] if kind == "outfits" else ["test"]
    if kind == "outfits":
        aliases = {"seen": "train", "unseen": "held_out", "all": None, "train": "train", "test": "held_out",
                   "held_out": "held_out", "test_seen": "test_seen", "test_unseen": "test_unseen"}
        if len(spec) == 1 and spec[0] in aliases:
            return outfit_names(aliases[spec[0]])
        return spec
    if spec in (["train"], ["test"]):
        return list_clips(spec[0])
    if spec == ["all"]:
        return list_clips()
    return spec


def make_report(results: list[RunResult], outfits: list[str], motions: list[str], shape: str,
                frames: int | None) -> str:
    """The markdown report: one table per method (Tables 1/3) and, for held-out outfits, per outfit (Table 2)."""
    text = [f"Outfits: {', '.join(outfits)}; clips: {', '.join(motions)}; shape {shape}; "
            f"frames per clip: {frames or 'full clip'} (at most)\n",
            markdown_table(aggregate(results), "Per method (paper Tables 1 and 3)")]
    unseen = [r for r in results if r.split != "train"]
    if unseen:
        text.append(markdown_table(aggregate(unseen, key="outfit"), "Per held-out outfit (paper Table 2)"))
    return "\n".join(text)


def add_model_rollout_options(p: argparse.ArgumentParser) -> None:
    """The options of a model's rollout shared by ``smln eval`` and ``smln rollout``: ``--project-body``,
    ``--project-layers`` (:mod:`smln.projection`), ``--precision`` (:mod:`smln.model.precision`) and ``--compile``
    (:mod:`smln.model.compiled`)."""
    p.add_argument("--project-body", action="store_true",
                   help="after each network step, move body-penetrating vertices back out (smln.projection)")
    p.add_argument("--project-layers", action="store_true",
                   help="after each network step, move each layer out of the one beneath (smln.projection)")
    p.add_argument("--precision", default="float32", choices=["float32", "bfloat16"],
                   help="processor precision (bfloat16: faster on CPUs with AMX / AVX512-BF16; smln.model.precision)")
    p.add_argument("--compile", action="store_true",
                   help="run the processor through torch.compile: 12-15%% faster steps on CPU after a one-off "
                        "10-80 s compilation (smln.model.compiled)")
    p.add_argument("--max-skin-distance", type=float, default=MAX_SKIN_DISTANCE, metavar="M",
                   help="a frame with a garment vertex farther than M meters from its skinned place falls back to "
                        "skinning (default %(default)s)")
    p.add_argument("--max-body-distance", type=float, default=MAX_BODY_DISTANCE, metavar="M",
                   help="a frame with a garment vertex farther than M meters from the body falls back to skinning "
                        "(default %(default)s)")
    p.add_argument("--repulsion-pairing", choices=REPULSION_PAIRINGS,
                   help="how the repulsion layer reads an outer vertex against the layer beneath, overriding the "
                        "checkpoint's: vertex (paper Eq. 14, the nearest inner vertex at t), deeper (also the closest "
                        "inner triangle point) or nearest (the inner vertex nearest to the prediction at t+1, the "
                        "L-Coll metric's pairing; SMLNConfig.repulsion_pairing); models without the layer are "
                        "unchanged")
    p.add_argument("--body-pairing", choices=BODY_PAIRINGS,
                   help="which body vertex the repulsion layer's body stage reads a garment vertex against, "
                        "overriding the checkpoint's: edge (its world edge's, nearest at t, as trained), nearest "
                        "(nearest to the prediction at t+1, the H-Coll metric's pairing) or edge_inside (the edge "
                        "pairs, then the nearest reading for the vertices still inside the body; "
                        "SMLNConfig.body_pairing); models without the body stage are unchanged")
    p.add_argument("--skin-guard", default="always", choices=SKIN_GUARDS,
                   help="always: --max-skin-distance alone means divergence; symptomatic: only with a symptom of a "
                        "tangle (mean strain > 10 %%, H-Coll > 5 %%) or beyond twice that distance "
                        "(smln.rollout.SKIN_GUARDS)")


def apply_repulsion_pairing(model, pairing: str | None) -> bool:
    """Set a loaded model's ``repulsion_pairing`` (``--repulsion-pairing``; None: leave the checkpoint's).

    Returns:
        True if the model has a repulsion layer and its reading changed.
    """
    if pairing is None or not model.config.use_repulsion_layer or model.config.repulsion_pairing == pairing:
        return False
    if pairing not in REPULSION_PAIRINGS:
        raise ValueError(f"repulsion pairing must be one of {REPULSION_PAIRINGS}, got {pairing!r}")
    model.config.repulsion_pairing = pairing
    return True


def apply_body_pairing(model, pairing: str | None) -> bool:
    """Set a loaded model's ``body_pairing`` (``--body-pairing``; None: leave the checkpoint's).

    Returns:
        True if the model has the body stage of the repulsion layer and its pairing changed.
    """
    if pairing is None or not (model.config.use_repulsion_layer and model.config.body_repulsion) \
            or model.config.body_pairing == pairing:
        return False
    if pairing not in BODY_PAIRINGS:
        raise ValueError(f"body pairing must be one of {BODY_PAIRINGS}, got {pairing!r}")
    model.config.body_pairing = pairing
    return True


def rollout_guards(a: argparse.Namespace) -> dict[str, float | str]:
    """The divergence bounds of :func:`add_model_rollout_options` as :func:`smln.rollout.rollout` keywords."""
    for flag, value in (("--max-skin-distance", a.max_skin_distance), ("--max-body-distance", a.max_body_distance)):
        if not value > 0:
            raise ValueError(f"{flag} must be a positive distance in meters, got {value}")
    return {"max_distance": a.max_skin_distance, "max_body_distance": a.max_body_distance,
            "skin_guard": a.skin_guard}


def load_results(paths: list[str | Path]) -> list[RunResult]:
    """The runs of one or more ``smln eval --json`` files, in order.

    Raises:
        ValueError: a file that is not such a list, or one method × outfit × clip present twice (two files
            of the same checkpoint, or a merged file given with its parts), which would count its frames twice.
    """
    results: list[RunResult] = []
    seen: dict[tuple[str, str, str], str] = {}
    for path in paths:
        try:
            rows = json.loads(Path(path).read_text())
            runs = [RunResult(r["method"], r["outfit"], r["motion"], r["split"], r["metrics"]) for r in rows]
        except (OSError, json.JSONDecodeError, TypeError, KeyError) as e:
            raise ValueError(f"{path}: not an `smln eval --json` output ({type(e).__name__}: {e})") from e
        for r in runs:
            key = (r.method, r.outfit, r.motion)
            if key in seen:
                raise ValueError(f"{path}: {r.method} on {r.outfit} × {r.motion} is also in {seen[key]}")
            seen[key] = str(path)
        results.extend(runs)
    return results


def cli_main(args: argparse.Namespace) -> None:
    main(args.argv)


def main(argv: list[str] | None = None) -> list[RunResult]:
    from smln.checkpoint import load_checkpoint

    p = argparse.ArgumentParser(prog="smln eval", description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", action="append", default=[], help="checkpoint path (repeatable)")
    p.add_argument("--outfits", nargs="+", help="seen | unseen | all | outfit names (default: seen)")
    p.add_argument("--motions", nargs="+", help="train | test | all | clip names (default: test)")
    p.add_argument("--shape", default=DEFAULT_SHAPE,
                   help="body shape preset: female_average, male_average, tall_heavy or petite_slim "
                        "(default: %(default)s)")
    p.add_argument("--frames", type=int, help="frames per clip (default: the whole clip)")
    p.add_argument("--edge-length", type=float, default=0.02)
    p.add_argument("--no-skinning", action="store_true", help="leave out the skinning-only row")
    p.add_argument("--surface-metrics", action="store_true",
                   help="also the point-to-triangle L-Coll / H-Coll (smln.metrics.behind_surface; ~80 ms per frame)")
    p.add_argument("--solver", action="store_true", help="add the reference L-BFGS solver (slow)")
    p.add_argument("--device", default="cpu")
    add_model_rollout_options(p)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", help="write all results as JSON")
    p.add_argument("--markdown", help="write the tables as markdown")
    p.add_argument("--from-json", nargs="+", metavar="JSON",
                   help="re-print the tables of earlier --json outputs (several are merged, e.g. one per checkpoint "
                        "and a skinning-only run) without running anything")
    a = p.parse_args(argv)
    if a.from_json:
        results = load_results(a.from_json)
        report = make_report(results, sorted({r.outfit for r in results}), sorted({r.motion for r in results}),
                             a.shape, a.frames)
        print(report)
        if a.markdown:
            Path(a.markdown).write_text(report)
        return results
    set_threads(a.threads)
    methods: dict[str, object | None] = {}
    repeated = sorted({ck for ck in a.checkpoint if a.checkpoint.count(ck) > 1})
    if repeated:
        raise ValueError(f"--checkpoint {repeated[0]} is given more than once")
    for ck in a.checkpoint:
        model, card = load_checkpoint(ck)
        name = card.get("variant") or Path(ck).name
        if a.project_body or a.project_layers:
            name += " + projection (" + "+".join(k for k, on in (("body", a.project_body),
                                                                  ("layers", a.project_layers)) if on) + ")"
        if a.precision != "float32":
            name += f" [{a.precision}]"
        if (a.max_skin_distance, a.max_body_distance) != (MAX_SKIN_DISTANCE, MAX_BODY_DISTANCE):
            name += f" [guard skin {a.max_skin_distance:g} m, body {a.max_body_distance:g} m]"
        if a.skin_guard != "always":
            name += f" [skin guard {a.skin_guard}]"
        if apply_repulsion_pairing(model, a.repulsion_pairing):
            name += f" [{a.repulsion_pairing} pairing]"
        if apply_body_pairing(model, a.body_pairing):
            name += f" [{a.body_pairing} body pairing]"
        if name in methods:  # two checkpoints of one variant (e.g. an old and a new `full`): name them by path
            name = f"{name} ({ck})"
        methods[name] = model
    if not a.no_skinning:
        methods["skinning"] = None
    if a.solver:
        methods["solver"] = None
    outfits = resolve_names(a.outfits, "outfits")
    motions = resolve_names(a.motions, "motions")
    results = evaluate(methods, outfits, motions, shape=a.shape, frames=a.frames, edge_length=a.edge_length,
                       device=a.device, project_body=a.project_body, project_layers=a.project_layers,
                       precision=a.precision, compiled=a.compile, surface_metrics=a.surface_metrics,
                       guards=rollout_guards(a))
    report = make_report(results, outfits, motions, a.shape, a.frames)
    print(report)
    if a.markdown:
        Path(a.markdown).write_text(report)
    if a.json:
        Path(a.json).write_text(json.dumps([{"method": r.method, "outfit": r.outfit, "motion": r.motion,
                                             "split": r.split, "metrics": r.metrics} for r in results], indent=1))
    return results
