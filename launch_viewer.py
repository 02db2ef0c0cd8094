"""Launch the SMLN browser viewer.

    python launch_viewer.py [--checkpoints DIR] [--host 127.0.0.1] [--port 8080] [--device cpu|cuda]
                            [--allow-remote] [--extra-rollout ROLLOUT.npz ...]

Binds to localhost unless ``--allow-remote`` is given (the viewer has no authentication: anyone who can reach
the port can drive it and upload files). Bodies ship as compact exports, so start-up takes seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from typing import Any

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description="SMLN viewer: live multi-layer garment rollouts in the browser")
    p.add_argument("--checkpoints", default="checkpoints",
                   help="directory holding full/, no_repulsion_layer/, baseline/ checkpoints")
    p.add_argument("--host", default="127.0.0.1", help="interface to bind (default: localhost only)")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--max-frames", type=int, default=300, help="frames computed per rollout at most")
    p.add_argument("--precision", default="auto", choices=["auto", "float32", "bfloat16"],
                   help="processor precision of the models (smln.model.precision); auto: bfloat16 on CPUs with "
                        "native bfloat16 (AMX / AVX512-BF16), else float32")
    p.add_argument("--compile", action="store_true",
                   help="run the models' message passing through torch.compile (smln.model.compiled): 10-20 %% "
                        "faster frames after a one-off compilation of 10-80 s in the first rollout")
    p.add_argument("--edge-length", type=float, default=None,
                   help="garment triangle size in m (default 0.035, the training resolution; 0.02 is finer and slower)")
    p.add_argument("--allow-remote", action="store_true",
                   help="allow binding to a non-local interface (no authentication: use on trusted networks)")
    p.add_argument("--reading", default="checkpoint",
                   help="the repulsion layer's reading the viewer starts with (the picker's values: checkpoint, "
                        "vertex, deeper, layer-nearest, body-edge, body-nearest, all-nearest, body-inside, "
                        "nearest-inside, as-trained; app.sources.READINGS); "
                        "with the shipped full checkpoint, all-nearest is the reading that meets the issue's six "
                        "target figures (docs/RESULTS.md, session 41)")
    p.add_argument("--extra-rollout", action="append", default=[], metavar="PATH",
                   help="a saved rollout NPZ (e.g. runs/physics/*.npz from bench/physics_reference.py) shown as one "
                        "more read-only variant on its own scene (repeatable)")
    return p.parse_args(argv)


def load_extras(paths: list[str], catalog: Any) -> tuple[Any, Any]:
    """Validate ``--extra-rollout`` files: a bad one is skipped with a one-line message on stderr.

    Returns:
        (:class:`app.extras.ExtraStore`, the first rollout's scene as a :class:`app.sources.Setting` if the
        catalog offers it, else None).
    """
    from app.extras import ExtraRolloutError, ExtraStore
    from app.sources import Setting

    store = ExtraStore()
    setting = None
    for path in paths:
        try:
            extra = store.add(path)
        except ExtraRolloutError as exc:
            print(f"launch_viewer: skipping --extra-rollout {exc}", file=sys.stderr)
            continue
        where = extra.scene_text()
        print(f"saved rollout: {extra.label} ({path}: {extra.num_frames} frames on {where})"
              + (f"; {extra.note}" if extra.note else ""))
        if setting is None and catalog is not None and None not in extra.scene:
            outfit, clip, shape = extra.scene
            if (outfit in {k for _, k in catalog.outfits()} and clip in {k for _, k in catalog.clips()}
                    and shape in catalog.shapes()):
                setting = Setting(outfit, clip, shape)
    return store, setting


def with_reading(setting: Any, reading: str, catalog: Any) -> Any:
    """The viewer's first scene read with ``--reading``: ``setting`` (or the catalog's default scene when None) with
    that reading; None (the app's default) when the reading is the checkpoint's own and no scene was chosen."""
    if reading == "checkpoint":
        return setting
    return dataclasses.replace(setting or catalog.default_setting(), reading=reading)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.host not in LOCAL_HOSTS and not args.allow_remote:
        print(f"launch_viewer: refusing to bind to {args.host}: the viewer has no authentication. "
              "Pass --allow-remote to expose it anyway.", file=sys.stderr)
        return 2
    if args.host not in LOCAL_HOSTS:
        print(f"WARNING: binding to {args.host}: anyone who can reach port {args.port} can drive this viewer "
              "and upload files.", file=sys.stderr)
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            print("launch_viewer: --device cuda but no CUDA device is available", file=sys.stderr)
            return 2

    t0 = time.perf_counter()
    from app.server import ViewerApp
    from app.sources import READINGS, VARIANT_LABELS, Catalog

    if args.reading not in READINGS:
        print(f"launch_viewer: --reading must be one of {', '.join(READINGS)}", file=sys.stderr)
        return 2

    if args.edge_length is not None and not 0.01 <= args.edge_length <= 0.1:
        print("launch_viewer: --edge-length must be between 0.01 and 0.1 m", file=sys.stderr)
        return 2
    from smln.model.precision import native_bfloat16

    precision = args.precision
    if precision == "auto":
        precision = "bfloat16" if args.device == "cpu" and native_bfloat16() else "float32"
    catalog = Catalog(args.checkpoints, device=args.device, max_frames=args.max_frames, edge_length=args.edge_length,
                      precision=precision, compiled=args.compile)
    print(f"model precision: {precision} processor" + (", compiled (the first rollout compiles it: 10-80 s)"
                                                       if args.compile else ""))
    if catalog.checkpoints:
        found = ", ".join(f"{VARIANT_LABELS[v]} ({p})" for v, p in catalog.checkpoints.items())
        print(f"checkpoints: {found}")
    else:
        print(f"no checkpoint found in {args.checkpoints}/ (expected full/, no_repulsion_layer/, baseline/): "
              "showing skinning-only rollouts")
    extras, setting = load_extras(args.extra_rollout, catalog)
    setting = with_reading(setting, args.reading, catalog)
    try:
        app = ViewerApp(host=args.host, port=args.port, catalog=catalog, device=args.device,
                        max_frames=args.max_frames, extras=extras, setting=setting)
    except OSError as exc:
        print(f"launch_viewer: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
    print(f"SMLN viewer ready in {time.perf_counter() - t0:.1f} s: open {app.url}  (Ctrl+C to stop)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        app.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
