"""The ``smln`` command line: list clips and outfits, pose bodies, run rollouts, train, evaluate, average
checkpoints, export.

Every sub-command turns the library's own errors (bad files, unknown names, tampered checkpoints) into one line
on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from smln.body.shapes import BODY_SHAPES, DEFAULT_SHAPE


def _cmd_motions(args: argparse.Namespace) -> None:
    from smln.motion import load_bvh, manifest
    from smln.motion.library import clip_path
    from smln.motion.resample import sample_times

    rows = []
    for c in manifest():
        clip = load_bvh(clip_path(c["name"]))
        frames = len(sample_times(clip.num_frames, clip.fps, 30))
        rows.append({"name": c["name"], "kind": c["kind"], "split": c["split"], "frames": frames,
                     "duration_s": round((frames - 1) / 30, 2)})
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    print(f"{'clip':40s} {'kind':10s} {'split':6s} {'frames':>6s} {'seconds':>8s}")
    for r in rows:
        print(f"{r['name']:40s} {r['kind']:10s} {r['split']:6s} {r['frames']:6d} {r['duration_s']:8.2f}")


def _cmd_body(args: argparse.Namespace) -> None:
    from smln.body import load_body
    from smln.motion import load_body_sequence

    body = load_body(args.shape)
    seq = load_body_sequence(args.motion, body, max_frames=args.frames)
    out = Path(args.out)
    if out.suffix != ".npz":  # numpy appends .npz: check the file that will really be written
        out = out.with_name(out.name + ".npz")
    _refuse_overwrite(out, args.force)
    np.savez_compressed(out, vertices=seq.vertices.numpy(), faces=seq.faces.numpy().astype(np.int32),
                        fps=np.array(seq.fps), shape=np.array(args.shape), motion=np.array(seq.name))
    print(f"wrote {out}: {seq.num_frames} frames of {seq.vertices.shape[1]} vertices at {seq.fps:g} fps")


def _cmd_outfits(args: argparse.Namespace) -> None:
    from smln.garments.export import outfits_table

    rows = outfits_table()
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    for r in rows:
        layers = " + ".join(f"{layer['type']} ({layer['vertices']} v)" for layer in r["layers"])
        print(f"{r['name']:26s} {r['split']:12s} {r['vertices']:6d} v {r['faces']:6d} f   {layers}")


def _cmd_outfit(args: argparse.Namespace) -> None:
    from smln.garments.export import export_outfit

    out = Path(args.out)
    _refuse_overwrite(out, args.force)
    export_outfit(args.name, args.shape, out)
    print(f"wrote {out}")


def _cmd_average(args: argparse.Namespace) -> None:
    from smln.checkpoint import average_checkpoints, checkpoint_files

    for target in checkpoint_files(args.out):
        _refuse_overwrite(target, args.force)
    card = average_checkpoints(args.checkpoints, args.out, weights=args.weights)
    print(f"wrote {card} (average of {len(args.checkpoints)} checkpoints)")


def _refuse_overwrite(path: Path, force: bool) -> None:
    if path.exists() and not force:
        raise FileExistsError(f"{path} exists; pass --force to overwrite it")


def _load_command(module: str, name: str) -> Callable[[argparse.Namespace], None]:
    def run(args: argparse.Namespace) -> None:
        import importlib

        getattr(importlib.import_module(module), name)(args)

    return run


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="smln", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("motions", help="list the shipped motion clips")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_motions)

    p = sub.add_parser("body", help="write a posed body sequence (vertices (T, Vb, 3), faces) to an NPZ")
    p.add_argument("--shape", default=DEFAULT_SHAPE, choices=list(BODY_SHAPES))
    p.add_argument("--motion", required=True, help="clip name (see `smln motions`) or path to a .bvh file")
    p.add_argument("--frames", type=int, default=None)
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    p.set_defaults(func=_cmd_body)

    p = sub.add_parser("outfits", help="list the outfits")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_outfits)

    p = sub.add_parser("outfit", help="export an outfit's dressed rest pose (.obj, .glb, .ply)")
    p.add_argument("name")
    p.add_argument("--shape", default=DEFAULT_SHAPE, choices=list(BODY_SHAPES))
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true")
    p.set_defaults(func=_cmd_outfit)

    p = sub.add_parser("average", help="average the weights of checkpoints fine-tuned from one parent (model soup)")
    p.add_argument("checkpoints", nargs="+", help="two or more checkpoints with the same config and buffers")
    p.add_argument("--out", required=True, help="stem or directory of the new checkpoint")
    p.add_argument("--weights", type=float, nargs="+", default=None, help="one weight per checkpoint (uniform)")
    p.add_argument("--force", action="store_true", help="overwrite an existing checkpoint")
    p.set_defaults(func=_cmd_average)

    for name, module, func, helptext in (
        ("rollout", "smln.rollout_cli", "main", "run a checkpoint over a clip and save the rollout NPZ"),
        ("train", "smln.train", "cli_main", "train a checkpoint (self-supervised)"),
        ("eval", "smln.evaluate", "cli_main", "evaluate checkpoints: the paper's tables"),
        ("export", "smln.export", "cli_main", "convert a rollout NPZ to OBJ sequence / PC2 / GLB"),
        ("select", "smln.selection", "cli_main", "rank checkpoints (a run's snapshots) by rollouts on training scenes"),
    ):
        p = sub.add_parser(name, help=helptext, add_help=False)
        p.set_defaults(func=_load_command(module, func))
    return parser


def _first_line(exc: BaseException) -> str:
    """The first line of an error message (the CLI prints exactly one line per error)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    if args.command in ("rollout", "train", "eval", "export", "select"):
        args.argv = rest
    elif rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    try:
        args.func(args)
    except (ValueError, FileNotFoundError, FileExistsError, OSError) as exc:
        print(f"smln {args.command}: error: {_first_line(exc)}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # CheckpointError (a RuntimeError); smln.checkpoint is loaded if it raised one
        checkpoint = sys.modules.get("smln.checkpoint")
        if checkpoint is None or not isinstance(exc, checkpoint.CheckpointError):
            raise
        print(f"smln {args.command}: error: {_first_line(exc)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
