"""SMLN checkpoints: weights and normaliser buffers as safetensors plus a JSON card. Never executes code.

Layout for a stem ``ckpt/run1`` (or a directory ``ckpt/run1/``, which holds ``model.safetensors`` and
``card.json``): ``ckpt/run1.safetensors`` + ``ckpt/run1.json``. The card holds the format name and version, the
architecture config (:class:`~smln.model.SMLNConfig`), the variant name, the training settings and the sha256 of
the tensor file. Loading validates, in order: both files exist, the tensor file is a safetensors file (a pickle
or zip renamed to ``.safetensors`` is refused before anything is parsed), the card's schema and version, the
sha256, every tensor name and shape against the config, and finiteness.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from smln.model.smln import SMLN, SMLNConfig

FORMAT = "smln-checkpoint"
VERSION = 1
LEGACY_CONFIG = {"body_normal_features": False}
"""Config values of cards written before the field existed (the field's default differs from what they ran)."""


class CheckpointError(RuntimeError):
    """A checkpoint is missing, malformed, tampered with or does not match its config."""


def checkpoint_files(path: str | Path) -> tuple[Path, Path]:
    """(tensor file, card file) of a checkpoint stem, either file name, or a directory."""
    p = Path(path)
    if p.is_dir() or str(path).endswith(("/", "\\")):
        return p / "model.safetensors", p / "card.json"
    if p.suffix in (".safetensors", ".json"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".safetensors"), p.with_name(p.name + ".json")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def save_checkpoint(path: str | Path, model: SMLN, config: SMLNConfig | None = None, card: dict | None = None) -> Path:
    """Write ``model``'s weights and buffers (normaliser statistics included) and a JSON card.

    Args:
        path: a stem (``ckpt/run1`` -> ``ckpt/run1.safetensors`` + ``.json``) or a directory.
        model: the network.
        config: its architecture (default ``model.config``).
        card: extra card fields, e.g. ``{"variant": "full", "training": {...}}``; ``variant`` defaults to
            ``"smln"``.

    Returns:
        Path of the JSON card.
    """
    config = config or model.config
    tensors_path, card_path = checkpoint_files(path)
    tensors_path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous().clone() for k, v in model.state_dict().items()}
    save_file(state, str(tensors_path), metadata={"format": FORMAT, "version": str(VERSION)})
    extra = dict(card or {})
    out: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "variant": extra.pop("variant", "smln"),
        "config": config.to_dict(),
        "training": extra.pop("training", {}),
        "smln_version": _package_version(),
        "tensors_file": tensors_path.name,
        "sha256": _sha256(tensors_path),
        "tensors": {k: list(v.shape) for k, v in state.items()},
    }
    out.update(extra)
    card_path.write_text(json.dumps(out, indent=2, sort_keys=True))
    return card_path


def _package_version() -> str:
    import smln

    return getattr(smln, "__version__", "unknown")


def _check_header(path: Path) -> None:
    """Refuse files that are not safetensors (pickles, torch zip archives) without parsing them."""
    with path.open("rb") as f:
        head = f.read(9)
    header_len = int.from_bytes(head[:8], "little") if len(head) == 9 else -1
    if head[8:9] == b"{" and 0 < header_len <= path.stat().st_size - 8:
        return  # safetensors: an 8-byte little-endian header length, then the JSON header (its low byte may be 0x80)
    if head[:1] == b"\x80" or head[:2] == b"PK":
        kind = "a pickle" if head[:1] == b"\x80" else "a zip archive (torch.save)"
        raise CheckpointError(f"{path} is {kind}, not safetensors; refusing to load it (pickles can run code)")
    if len(head) < 9 or head[8:9] != b"{":
        raise CheckpointError(f"{path} is not a safetensors file (bad header)")


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> tuple[SMLN, dict]:
    """Load and validate a checkpoint written by :func:`save_checkpoint`.

    Args:
        path: the stem, either file, or the directory.
        map_location: device of the returned model.

    Returns:
        (model in eval mode, card dict).

    Raises:
        CheckpointError: with a message naming what is wrong.
    """
    tensors_path, card_path = checkpoint_files(path)
    if not card_path.is_file():
        raise CheckpointError(f"checkpoint card not found: {card_path}")
    if not tensors_path.is_file():
        raise CheckpointError(f"checkpoint tensors not found: {tensors_path}")
    _check_header(tensors_path)
    try:
        card = json.loads(card_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{card_path}: not valid JSON ({e})") from e
    if not isinstance(card, dict) or card.get("format") != FORMAT:
        raise CheckpointError(f"{card_path}: not an {FORMAT} card")
    if card.get("version") != VERSION:
        raise CheckpointError(f"{card_path}: unsupported version {card.get('version')!r} (expected {VERSION})")
    for key in ("config", "sha256"):
        if key not in card:
            raise CheckpointError(f"{card_path}: missing field {key!r}")
    digest = _sha256(tensors_path)
    if digest != card["sha256"]:
        raise CheckpointError(
            f"{tensors_path}: sha256 mismatch (file {digest[:12]}..., card {str(card['sha256'])[:12]}...): "
            "the weights were modified or belong to another card"
        )
    try:
        config = SMLNConfig.from_dict({**LEGACY_CONFIG, **card["config"]})
        model = SMLN(config)  # the card is not covered by the sha256: a hand-edited config fails here
    except (TypeError, ValueError, RuntimeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{card_path}: invalid config ({first[:200]})") from None
    expected = model.state_dict()
    try:
        with safe_open(str(tensors_path), framework="pt") as f:
            names = set(f.keys())
            missing = sorted(set(expected) - names)
            unexpected = sorted(names - set(expected))
            if missing or unexpected:
                raise CheckpointError(
                    f"{tensors_path}: tensor names do not match the config (missing {missing[:5]}, "
                    f"unexpected {unexpected[:5]})"
                )
            state = {}
            for name in sorted(names):
                t = f.get_tensor(name)
                if tuple(t.shape) != tuple(expected[name].shape) or t.dtype != expected[name].dtype:
                    raise CheckpointError(
                        f"{tensors_path}: tensor {name!r} is {tuple(t.shape)} {t.dtype}, the config needs "
                        f"{tuple(expected[name].shape)} {expected[name].dtype}"
                    )
                if t.is_floating_point() and not torch.isfinite(t).all():
                    raise CheckpointError(f"{tensors_path}: tensor {name!r} contains NaN or Inf")
                state[name] = t
    except SafetensorError as e:
        raise CheckpointError(f"{tensors_path}: unreadable safetensors file ({e})") from e
    model.load_state_dict(state, strict=True)
    return model.to(map_location).eval(), card


def average_checkpoints(paths: list[str | Path], out: str | Path, weights: list[float] | None = None) -> Path:
    """Write the weighted average of several checkpoints' parameters (a "model soup") as a new checkpoint.

    Averaging only makes sense for runs fine-tuned from one common parent (the same loss basin), so the inputs
    must share the architecture config, the variant and every buffer (the normaliser statistics and the output
    scale: the first layers were trained on inputs scaled by them). Parameters are averaged in float64 and
    stored in their own dtype.

    Args:
        paths: two or more checkpoints (stems, files or directories, as :func:`load_checkpoint` takes).
        out: the stem or directory to write (as :func:`save_checkpoint` takes).
        weights: one non-negative weight per checkpoint (normalised to sum 1); default uniform.

    Returns:
        Path of the written JSON card. Its ``averaged_from`` lists each input (path, sha256, weight, steps, wall
        time, training settings); ``training.steps`` is the largest input's and ``training.wall_time_s`` the sum.

    Raises:
        CheckpointError: an input fails :func:`load_checkpoint`.
        ValueError: fewer than two inputs, bad weights, or inputs that differ in config, variant or buffers.
    """
    if len(paths) < 2:
        raise ValueError("averaging needs at least two checkpoints")
    w = torch.tensor([1.0] * len(paths) if weights is None else [float(x) for x in weights], dtype=torch.float64)
    if w.numel() != len(paths) or not torch.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
        raise ValueError(f"need one non-negative weight per checkpoint ({len(paths)}), got {weights}")
    w = w / w.sum()
    loaded = [load_checkpoint(p) for p in paths]
    first_model, first_card = loaded[0]
    for (_, card), path in zip(loaded[1:], paths[1:], strict=True):
        if card["config"] != first_card["config"]:
            raise ValueError(f"{path}: its architecture config differs from {paths[0]}'s; cannot average")
        if card.get("variant") != first_card.get("variant"):
            raise ValueError(f"{path}: variant {card.get('variant')!r} differs from {first_card.get('variant')!r}")
    buffer_names = {name for name, _ in first_model.named_buffers()}
    states = [m.state_dict() for m, _ in loaded]
    averaged = {}
    for name, value in states[0].items():
        if name in buffer_names:
            for state, path in zip(states[1:], paths[1:], strict=True):
                if not torch.equal(state[name], value):
                    raise ValueError(f"{path}: buffer {name!r} differs from {paths[0]}'s (normaliser statistics "
                                     "must match: average only runs fine-tuned from one parent)")
            averaged[name] = value
        else:
            stacked = torch.stack([s[name].to(torch.float64) for s in states])
            averaged[name] = torch.tensordot(w, stacked, dims=1).to(value.dtype)
    first_model.load_state_dict(averaged, strict=True)
    cards = [c for _, c in loaded]
    trainings = [c.get("training", {}) for c in cards]
    training = {key: trainings[0].get(key) for key in ("hardware", "torch", "device", "processes", "variant")}
    training["method"] = "weighted average of the parameters of the checkpoints in averaged_from"
    training["steps"] = max(int(t.get("steps") or 0) for t in trainings)
    training["wall_time_s"] = round(sum(float(t.get("wall_time_s") or 0.0) for t in trainings), 1)
    card_out: dict[str, Any] = {
        "variant": first_card.get("variant", "smln"),
        "training": training,
        "weights": "weighted average of the inputs' stored weights",
        "averaged_from": [
            {"path": str(p), "sha256": c["sha256"], "weight": float(wi), "steps": t.get("steps"),
             "wall_time_s": t.get("wall_time_s"), "loss_weights": c.get("loss_weights"), "training": t,
             "initialised_from": c.get("initialised_from")}
            for p, c, t, wi in zip(paths, cards, trainings, w.tolist(), strict=True)
        ],
    }
    if all(c.get("loss_weights") == first_card.get("loss_weights") for c in cards):
        card_out["loss_weights"] = first_card.get("loss_weights")
    parents = [c.get("initialised_from") for c in cards]
    if parents[0] is not None and all(p == parents[0] for p in parents):
        card_out["initialised_from"] = parents[0]  # the common parent: the lineage the model cards print
    return save_checkpoint(out, first_model, card=card_out)
