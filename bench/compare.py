"""SMLN against a physics simulator and our own energy-minimisation solver, on the same outfits and clips.

``python bench/compare.py --frames 20 --json runs/compare.json --markdown docs/BENCHMARKS.md``

For each outfit x test clip (default: the 2-layer ``tshirt_jacket`` and the 3-layer ``tshirt_longsleeve_jacket``
on ``05_01_walk`` and ``02_05_punch_strike``, training edge length 0.035 m, body ``female_average``), one row per
method. Started from the skinned frame 1 the physics reference tore the cloth on fast and 3-layer scenes: hence the
lead-in (``physics_reference.py --preroll``). On ``09_06_run`` (12.6 cm/frame, 6 mm per substep at 20 substeps)
the body still passes through the cloth and leaves it behind, so that clip needs more substeps than we can afford
on 2 cores; the punch (0.9 cm/frame body speed, fists up to 7 cm/frame) is the second clip.

- ``SMLN (full)``, ``no_repulsion_layer``, ``baseline``: the trained checkpoints (``checkpoints/<variant>`` if
  published, else ``runs/<variant>/best``), :func:`smln.rollout.rollout` with fallback;
- ``SMLN (full) + projection`` (with ``--projection``): the full model followed by the body and layer collision
  projection of :mod:`smln.projection` after every step;
- ``skinning``: garments rigidly skinned, no dynamics;
- ``L-BFGS solver``: :mod:`smln.solver`, the same per-step loss minimised per frame, no network;
- ``physics (Newton VBD)``: ``bench/physics_reference.py`` with a ``--preroll`` lead-in from the T-pose (default
  40 frames; read from ``--physics-dir`` when a long enough rollout
  NPZ is there, else simulated now).

Columns: ms/frame (median over the simulated frames), speed-up over physics (physics ms / method ms), L-Coll %,
H-Coll % (mean over frames; LayersNet's nearest-vertex tests), the same against the closest point on the inner
layers' / body's triangles (``surf.``, :func:`smln.metrics.behind_surface`), mean / max edge strain, and the
mean vertex distance to the physics result (mm, over frames and vertices). All statistics use frames 2 .. N-1
(frames 0-1 are the skinned initial state of the network rollouts). Plots of H-Coll, L-Coll and the distance to
physics over time go to ``benchmarks/*.png`` beside the ``--markdown`` report (or the ``--json``; else
``runs/benchmarks``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from smln.body import DEFAULT_SHAPE  # noqa: E402
from smln.data_sampling import make_scene  # noqa: E402
from smln.evaluate import method_frames  # noqa: E402
from smln.export import load_rollout_npz, save_rollout_npz  # noqa: E402
from smln.garments import TRAINING_EDGE_LENGTH  # noqa: E402
from smln.geometry import set_threads  # noqa: E402
from smln.metrics import surface_h_coll, surface_l_coll  # noqa: E402

VARIANTS = (("SMLN (full)", "full"), ("no_repulsion_layer", "no_repulsion_layer"), ("baseline", "baseline"))
PHYSICS = "physics (Newton VBD)"
PROJECTED = "SMLN (full) + projection"
FIRST = 2
"""First frame in the statistics (frames 0-1 are the skinned initial state of the network rollouts)."""


def cpu_model() -> str:
    """The CPU model name (``/proc/cpuinfo`` or ``lscpu``)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        for line in out.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def find_checkpoint(variant: str, root: Path) -> Path | None:
    """``checkpoints/<variant>`` if published, else the stem ``runs/<variant>/best``, else None."""
    pub = root / "checkpoints" / variant
    if pub.is_dir() and any(pub.glob("*.safetensors")):
        return pub
    best = root / "runs" / variant / "best"
    if best.with_suffix(".safetensors").exists():
        return best
    return None


def physics_rollout(scene, frames: int, physics_dir: Path, substeps: int, iterations: int, preroll: int = 0):
    """The physics reference of a scene: a cached NPZ with >= ``frames`` frames, else simulated and saved.

    ``preroll`` > 0: the garments are simulated from their rest shape through a lead-in from the T-pose
    (``physics_reference.py --preroll``); cached under a separate name.

    Returns:
        (positions (T, V, 3) float32, per-frame metric dicts, meta dict, source description).
    """
    path = physics_dir / (f"{scene.outfit}__{scene.motion}" + (f"__preroll{preroll}" if preroll else "") + ".npz")
    if path.exists():
        r = load_rollout_npz(path)
        if r.num_frames >= frames and r.num_vertices == scene.cloth.num_vertices:
            rows = [{k: float(r.metrics[t, i]) for i, k in enumerate(r.metric_names)} for t in range(frames)]
            return r.garment_positions[:frames], rows, r.meta, f"{path} (cached)"
    from physics_reference import physics_frames

    out = list(physics_frames(scene, frames, substeps=substeps, iterations=iterations, preroll=preroll))
    import newton

    meta = {"outfit": scene.outfit, "clip": scene.motion, "shape": scene.shape, "variant": PHYSICS,
            "newton_version": newton.__version__, "substeps": substeps, "iterations": iterations,
            "preroll": preroll, "ms_preroll": out[0].metrics.get("ms_preroll", 0.0)}
    physics_dir.mkdir(parents=True, exist_ok=True)
    save_rollout_npz(path, out, scene.cloth, scene.body.faces, meta=meta)
    return np.stack([f.garment_positions for f in out]), [f.metrics for f in out], meta, f"{path} (simulated now)"


def surface_series(x: np.ndarray, scene) -> tuple[list[float], list[float]]:
    """Per-frame point-to-triangle L-Coll and H-Coll (%) of positions x (T, V, 3) on ``scene``
    (:func:`smln.metrics.surface_l_coll`, :func:`smln.metrics.surface_h_coll`)."""
    faces, li = scene.cloth.faces.numpy(), scene.cloth.layer_index.numpy()
    body, body_faces = scene.body.vertices.numpy(), scene.body.faces.numpy()
    lc = [surface_l_coll(x[t], faces, li) for t in range(len(x))]
    hc = [surface_h_coll(x[t], body[t], body_faces) for t in range(len(x))]
    return lc, hc


def stats(rows: list[dict[str, float]], x: np.ndarray, x_phys: np.ndarray | None, scene=None) -> dict:
    """Table statistics over frames FIRST .. N-1.

    Args:
        rows: per-frame metric dicts (``ms_model``, optional ``ms_projection``, ``l_coll``, ``h_coll``,
            ``strain_mean``, ``strain_max``).
        x: (T, V, 3) positions, m; x_phys: (T, V, 3) physics positions, m (or None).

    Returns:
        dict with ms (median ms/frame), l_coll, h_coll (%, mean), strain_mean (mean), strain_max (max),
        dist_mm (mean vertex distance to physics, mm), with a ``scene`` also l_coll_surface / h_coll_surface (%,
        the point-to-triangle tests), and the per-frame series ``series`` (key -> list).
    """
    sel = rows[FIRST:]
    dist = np.linalg.norm(x - x_phys, axis=-1).mean(axis=1) * 1e3 if x_phys is not None else None
    lc_s, hc_s = surface_series(x, scene) if scene is not None else ([float("nan")] * len(x),) * 2
    return {
        "l_coll_surface": float(np.mean(lc_s[FIRST:])),
        "h_coll_surface": float(np.mean(hc_s[FIRST:])),
        # the simulation step (graph, network, repulsion layer) plus the collision projection if any; the
        # per-frame evaluation metrics are not part of a step (the physics time excludes them too)
        "ms": float(np.median([r["ms_model"] + r.get("ms_projection", 0.0) for r in sel])),
        "l_coll": float(np.mean([r["l_coll"] for r in sel])),
        "h_coll": float(np.mean([r["h_coll"] for r in sel])),
        "strain_mean": float(np.mean([r["strain_mean"] for r in sel])),
        "strain_max": float(np.max([r["strain_max"] for r in sel])),
        "dist_mm": float(dist[FIRST:].mean()) if dist is not None else float("nan"),
        "fallback_frames": int(sum(r.get("fallback", 0.0) for r in sel)),
        "series": {
            "h_coll": [r["h_coll"] for r in rows],
            "l_coll": [r["l_coll"] for r in rows],
            "l_coll_surface": list(lc_s),
            "h_coll_surface": list(hc_s),
            "strain_mean": [r["strain_mean"] for r in rows],
            "dist_mm": dist.tolist() if dist is not None else [],
        },
    }


def run_method(kind: str, model, scene, frames: int, projection: bool = False, precision: str = "float32",
               compiled: bool = False) -> tuple[np.ndarray, list[dict[str, float]]]:
    """Positions (T, V, 3) and per-frame metric dicts of one method (``fallback`` added as 0/1); ``projection``:
    the model's rollout uses the body and layer collision projection (:mod:`smln.projection`); ``precision``: the
    models' processor precision (:mod:`smln.model.precision`); ``compiled``: their processor through torch.compile
    (:mod:`smln.model.compiled`; the compilation lands in the first step, outside the median)."""
    xs, rows = [], []
    for fr in method_frames(kind, model, scene, frames, project_body=projection, project_layers=projection,
                            precision=precision, compiled=compiled):
        xs.append(np.asarray(fr.garment_positions, np.float32))
        m = dict(fr.metrics)
        m["fallback"] = float(fr.fallback)
        rows.append(m)
    return np.stack(xs), rows


def plot_scene(path: Path, title: str, results: dict[str, dict]) -> None:
    """H-Coll, L-Coll and distance to physics over time, one line per method (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for name, r in results.items():
        s = r["series"]
        t = np.arange(len(s["h_coll"]))
        style = "k-" if name == PHYSICS else "-"
        axes[0].plot(t, s["h_coll"], style, label=name)
        axes[1].plot(t, s["l_coll"], style, label=name)
        if s["dist_mm"]:
            axes[2].plot(t, s["dist_mm"], style, label=name)
    for ax, lab in zip(axes, ("H-Coll % (body)", "L-Coll % (layers)", "mean distance to physics (mm)"), strict=True):
        ax.set_xlabel("frame (30 fps)")
        ax.set_title(lab)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def markdown(report: dict) -> str:
    """The BENCHMARKS.md text: environment, one table over all scenes, per-scene tables and plots."""
    env = report["environment"]
    lines = [
        "# Benchmarks: SMLN against a physics simulator",
        "",
        "Generated by `python bench/compare.py` (" + report["command"] + "). Figures measured in one run on one "
        "machine:",
        "",
        f"- CPU: {env['cpu']}, {env['cores']} cores; torch {env['torch']} with {env['torch_threads']} threads; "
        f"Newton {env.get('newton', '?')} (Warp CPU kernels, one thread).",
        f"- Date: {env['date']}. " + env.get("note", ""),
        f"- Scenes: body `{report['shape']}`, outfits at the training edge length {report['edge_length']} m, "
        f"{report['frames']} frames per clip; statistics over frames {FIRST}..{report['frames'] - 1}.",
        "- Checkpoints: " + ", ".join(f"`{k}` from `{v}`" for k, v in report["checkpoints"].items())
        + f"; processor precision {report.get('precision', 'float32')} (`smln.model.precision`)"
        + ("; processor compiled with torch.compile (`smln.model.compiled`; the one-off compilation falls in the "
           "first simulated frame, outside the median)." if report.get("compiled") else "; processor eager."),
        "- Physics reference: Newton `SolverVBD` (substeps x iterations per frame in each scene's heading; "
        f"simulated now with {report['physics']['substeps']} x {report['physics']['iterations']} when no cached "
        "rollout), body = moving mesh collider, self-contact on (see `bench/physics_reference.py`); "
        + (f"the garments start at rest in the T-pose and are simulated through a {report['physics']['preroll']}-frame "
           "lead-in to the clip's frame 1 (`--preroll`), while the learned models start from skinning."
           if report["physics"].get("preroll") else "it starts from the skinned frame 1 like the learned models."),
        "",
        "Columns: ms/frame (median, simulated frames only), speed-up = physics ms / method ms, L-Coll / H-Coll "
        "(% of vertices, mean over frames; LayersNet's tests against the nearest inner/body *vertex* and its normal), "
        "L-Coll / H-Coll surf. (the same, against the closest point on the inner layers' / body's *triangles*; a "
        "closest point on an inner layer's hem is not a collision; `smln.metrics.behind_surface`), mean / max edge "
        "strain |l/l0 - 1| (%), distance = mean vertex distance to the physics result (mm).",
        "",
    ]
    head = ("| method | ms/frame | speed-up vs physics | L-Coll % | H-Coll % | L-Coll surf. % | H-Coll surf. % "
            "| strain mean % | strain max % | dist. to physics (mm) | fallback frames |")
    sep = "|" + "---|" * 11

    def row(name: str, r: dict) -> str:
        return (f"| {name} | {r['ms']:.0f} | {r['speedup']:.0f}x | {r['l_coll']:.2f} | {r['h_coll']:.2f} "
                f"| {r.get('l_coll_surface', float('nan')):.2f} | {r.get('h_coll_surface', float('nan')):.2f} "
                f"| {100 * r['strain_mean']:.2f} | {100 * r['strain_max']:.1f} | {r['dist_mm']:.1f} "
                f"| {r['fallback_frames']} |")

    lines += ["## All scenes (mean over scenes; strain max = max)", "", head, sep]
    for name, r in report["overall"].items():
        lines.append(row(name, r))
    for key, scene in report["scenes"].items():
        ph = scene.get("physics") or report["physics"]
        lines += ["", f"## {key} ({scene['vertices']} cloth vertices, {scene['layers']} layers; physics "
                  f"{ph.get('substeps')} substeps x {ph.get('iterations')} iterations"
                  + (f", {ph['preroll']}-frame lead-in" if ph.get("preroll") else "") + ")", "", head, sep]
        for name, r in scene["methods"].items():
            lines.append(row(name, r))
        lines += ["", f"![{key}](benchmarks/{scene['plot']})"]
    lines += ["", "## Notes", ""] + [f"- {n}" for n in report["notes"]]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=20, help="frames per clip (incl. the 2 skinned initial frames)")
    p.add_argument("--outfits", nargs="+", default=["tshirt_jacket", "tshirt_longsleeve_jacket"])
    p.add_argument("--clips", nargs="+", default=["05_01_walk", "02_05_punch_strike"])
    p.add_argument("--shape", default=DEFAULT_SHAPE)
    p.add_argument("--edge-length", type=float, default=TRAINING_EDGE_LENGTH)
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--physics-dir", default="runs/physics",
                   help="cached physics rollouts (outfit__clip[__prerollN].npz)")
    p.add_argument("--substeps", type=int, default=20)
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--preroll", type=int, default=40,
                   help="physics lead-in frames from the T-pose rest garments to frame 1 (0: start from skinning)")
    p.add_argument("--no-solver", action="store_true", help="leave out the L-BFGS solver (slow)")
    p.add_argument("--precision", default="float32", choices=["float32", "bfloat16"],
                   help="processor precision of the SMLN rows (bfloat16: CPUs with AMX / AVX512-BF16)")
    p.add_argument("--compile", action="store_true",
                   help="SMLN rows with the processor through torch.compile (smln.model.compiled)")
    p.add_argument("--projection", action="store_true",
                   help=f"add a row: {PROJECTED}, the full model with the collision projection of smln.projection")
    p.add_argument("--json", help="write all figures as JSON")
    p.add_argument("--markdown", help="write the report (e.g. docs/BENCHMARKS.md); plots go to benchmarks/ beside it")
    p.add_argument("--note", default="", help="free text for the environment line (e.g. other load)")
    p.add_argument("--notes", nargs="*", default=[], help="lines for the report's Notes section")
    a = p.parse_args(argv)
    set_threads(a.threads)
    root = Path.cwd()
    from smln.checkpoint import load_checkpoint

    models, sources = {}, {}
    for name, variant in VARIANTS:
        ck = find_checkpoint(variant, root)
        if ck is None:
            print(f"no checkpoint for {variant} (checkpoints/{variant} or runs/{variant}/best): skipped", flush=True)
            continue
        models[name], _ = load_checkpoint(ck)
        sources[variant] = str(ck)
        print(f"{name}: {ck}", flush=True)
    # plots beside the report (or the JSON); never into docs/ unless the report goes there
    out_file = a.markdown or a.json
    plot_dir = Path(out_file).parent / "benchmarks" if out_file else Path("runs/benchmarks")
    try:
        import newton

        newton_version = newton.__version__
    except ImportError:
        newton_version = "missing"
    report = {
        "command": "python bench/compare.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "environment": {"cpu": cpu_model(), "cores": os.cpu_count(),
                        "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
                        "newton": newton_version, "python": platform.python_version(),
                        "date": time.strftime("%Y-%m-%d %H:%M"), "note": a.note},
        "shape": a.shape, "edge_length": a.edge_length, "frames": a.frames, "checkpoints": sources,
        "precision": a.precision, "compiled": a.compile,
        "physics": {"substeps": a.substeps, "iterations": a.iterations, "preroll": a.preroll}, "scenes": {},
        "notes": list(a.notes),
    }
    for clip in a.clips:
        for outfit in a.outfits:
            scene = make_scene(outfit, a.shape, clip, edge_length=a.edge_length, max_frames=a.frames)
            n = scene.num_frames
            key = f"{outfit} / {clip}"
            print(f"{key}: {scene.cloth.num_vertices} vertices, {n} frames", flush=True)
            x_phys, rows_phys, phys_meta, src = physics_rollout(scene, n, Path(a.physics_dir), a.substeps,
                                                                a.iterations, a.preroll)
            print(f"  {PHYSICS}: {src}", flush=True)
            results = {}
            methods: list[tuple[str, str, object]] = [(k, "model", m) for k, m in models.items()]
            if a.projection and "SMLN (full)" in models:
                methods.insert(1, (PROJECTED, "projected", models["SMLN (full)"]))
            methods.append(("skinning", "skinning", None))
            if not a.no_solver:
                methods.append(("L-BFGS solver (no network)", "solver", None))
            for name, kind, model in methods:
                t0 = time.time()
                x, rows = run_method("model" if kind == "projected" else kind, model, scene, n,
                                     projection=kind == "projected", precision=a.precision,
                                     compiled=a.compile)
                results[name] = stats(rows, x, x_phys, scene)
                r = results[name]
                print(f"  {name:28s} {r['ms']:8.0f} ms/frame  L-Coll {r['l_coll']:.2f}%  H-Coll {r['h_coll']:.2f}% "
                      f" dist {r['dist_mm']:.1f} mm  ({time.time() - t0:.0f} s)", flush=True)
            results[PHYSICS] = stats(rows_phys, x_phys, x_phys, scene)
            r = results[PHYSICS]
            print(f"  {PHYSICS:28s} {r['ms']:8.0f} ms/frame  L-Coll {r['l_coll']:.2f}%  H-Coll {r['h_coll']:.2f}%",
                  flush=True)
            for r in results.values():
                r["speedup"] = results[PHYSICS]["ms"] / max(r["ms"], 1e-3)
            plot = f"{outfit}__{clip}.png"
            plot_scene(plot_dir / plot, f"{key} ({scene.cloth.num_vertices} cloth vertices)", results)
            report["scenes"][key] = {"outfit": outfit, "clip": clip, "vertices": scene.cloth.num_vertices,
                                     "layers": scene.cloth.num_layers, "plot": plot, "methods": results,
                                     "physics": {k: phys_meta.get(k) for k in ("substeps", "iterations", "preroll")}}
    names = list(next(iter(report["scenes"].values()))["methods"])
    overall = {}
    for name in names:
        rs = [s["methods"][name] for s in report["scenes"].values() if name in s["methods"]]
        overall[name] = {k: float(np.mean([r[k] for r in rs])) for k in
                         ("ms", "speedup", "l_coll", "h_coll", "l_coll_surface", "h_coll_surface", "strain_mean",
                          "dist_mm")}
        overall[name]["strain_max"] = float(max(r["strain_max"] for r in rs))
        overall[name]["fallback_frames"] = int(sum(r["fallback_frames"] for r in rs))
    report["overall"] = overall
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(report, indent=1))
    if a.markdown:
        Path(a.markdown).write_text(markdown(report))
        print(f"wrote {a.markdown} and plots in {plot_dir}", flush=True)
    return report


if __name__ == "__main__":
    main()
