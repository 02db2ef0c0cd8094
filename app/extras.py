"""Saved rollouts shown as extra, read-only variants (``launch_viewer.py --extra-rollout PATH``, or uploaded).

A rollout NPZ (:mod:`smln.export`, e.g. the Newton physics reference from ``bench/physics_reference.py``) is
validated on load (:func:`load_extra`: :func:`smln.export.load_rollout_npz` plus shape, range, size and
finiteness checks) and kept as an :class:`ExtraRollout`: its own faces, layer index, body and per-frame arrays,
turned into :class:`smln.rollout.RolloutFrame` objects once. It is drawn from its own arrays, so its resolution
need not match the viewer's garments; it is shown only on the scene (outfit, clip, body shape) named in its
``meta``. A refused file raises :class:`ExtraRolloutError` with a one-line message.
"""

from __future__ import annotations

import io
import threading
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from smln.export import ExportError, Rollout, load_rollout_npz
from smln.rollout import RolloutFrame

EXTRA_PREFIX = "extra:"
"""Variant keys of saved rollouts: ``extra:<n>``."""
MAX_ROLLOUT_UPLOAD_BYTES = 64 * 1024 * 1024
"""Largest accepted rollout NPZ upload (64 MB compressed)."""
MAX_ROLLOUT_ARRAY_BYTES = 1024**3
"""Largest total uncompressed size of a rollout NPZ's arrays (1 GiB; guards against zip bombs)."""
MAX_EXTRAS = 8
"""Saved rollouts one viewer holds at most."""
SCENE_KEYS = ("outfit", "clip", "shape")


class ExtraRolloutError(ValueError):
    """A saved rollout was refused; the message says why in one line."""


@dataclass
class Geometry:
    """What a variant's meshes are built from.

    Attributes:
        layer_vertices: per garment layer, the indices (or slice) of its vertices in a frame's positions.
        layer_faces: per layer, (F_k, 3) faces into that layer's vertices.
        body_faces: (Fb, 3) body triangles.
        garment0, body0: (V, 3) and (Vb, 3) positions the meshes start from, m.
    """

    layer_vertices: list[Any]
    layer_faces: list[np.ndarray]
    body_faces: np.ndarray
    garment0: np.ndarray
    body0: np.ndarray


@dataclass
class ExtraRollout:
    """A validated saved rollout.

    Attributes:
        key: variant key (``extra:<n>``); label: display name from its meta (e.g. "physics (Newton VBD)");
        source: file name it came from; rollout: the arrays; frames: one RolloutFrame per stored frame;
        geometry: its own meshes; scene: (outfit, clip, shape) from its meta (None where not recorded);
        note: why frames were dropped at load ("" if none).
    """

    key: str
    label: str
    source: str
    rollout: Rollout
    frames: list[RolloutFrame]
    geometry: Geometry
    scene: tuple[str | None, str | None, str | None]
    note: str = ""

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    def matches(self, setting: Any) -> bool:
        """True if the rollout was made on ``setting`` (keys missing from its meta are not compared)."""
        if setting is None:
            return False
        return all(want is None or want == getattr(setting, name)
                   for name, want in zip(SCENE_KEYS, self.scene, strict=True))

    def scene_text(self) -> str:
        """"outfit / clip / shape" as recorded in its meta."""
        return " / ".join(s if s is not None else "?" for s in self.scene)


def _label(meta: dict[str, Any], source: str) -> str:
    name = str(meta.get("variant") or Path(source).stem or "saved rollout")
    return name[:60]


def _check_size(data: bytes | Path, source: str) -> None:
    try:
        with zipfile.ZipFile(io.BytesIO(data) if isinstance(data, bytes) else data) as zf:
            total = sum(info.file_size for info in zf.infolist())
    except (OSError, zipfile.BadZipFile, ValueError) as exc:
        raise ExtraRolloutError(f"{source}: not a rollout NPZ ({str(exc) or type(exc).__name__})") from exc
    if total > MAX_ROLLOUT_ARRAY_BYTES:
        raise ExtraRolloutError(f"{source}: {total / 2**20:.0f} MB of arrays is over the "
                                f"{MAX_ROLLOUT_ARRAY_BYTES / 2**20:.0f} MB limit")


def _validate(r: Rollout, source: str) -> tuple[int, str]:
    """Shape checks beyond :func:`load_rollout_npz`; returns (frames kept, note)."""
    t, v = r.garment_positions.shape[:2]
    vb = r.body_vertices.shape[1] if r.body_vertices.ndim == 3 else -1
    problems = []
    if r.body_vertices.ndim != 3 or r.body_vertices.shape[2] != 3:
        problems.append(f"body_vertices {r.body_vertices.shape} is not (T, Vb, 3)")
    if r.faces.ndim != 2 or r.faces.shape[1] != 3 or len(r.faces) == 0:
        problems.append(f"faces {r.faces.shape} is not (F, 3)")
    if r.body_faces.ndim != 2 or r.body_faces.shape[1] != 3 or len(r.body_faces) == 0:
        problems.append(f"body_faces {r.body_faces.shape} is not (Fb, 3)")
    elif r.body_faces.min() < 0 or r.body_faces.max() >= vb:
        problems.append(f"body_faces index outside the {vb} body vertices")
    if r.repulsion_acceleration.shape != (t, v, 3):
        problems.append(f"repulsion_acceleration {r.repulsion_acceleration.shape} is not {(t, v, 3)}")
    for name in ("layer_penetration", "body_penetration"):
        if getattr(r, name).shape != (t, v):
            problems.append(f"{name} {getattr(r, name).shape} is not {(t, v)}")
    if r.metrics.shape != (t, len(r.metric_names)):
        problems.append(f"metrics {r.metrics.shape} does not match {t} frames x {len(r.metric_names)} names")
    if r.layer_index.size and (r.layer_index.min() < 0 or r.layer_index.max() >= 64):
        problems.append("layer_index outside 0..63")
    if problems:
        raise ExtraRolloutError(f"{source}: {problems[0]}")
    finite = np.isfinite(r.garment_positions).all(axis=(1, 2)) & np.isfinite(r.body_vertices).all(axis=(1, 2))
    if not finite[0]:
        raise ExtraRolloutError(f"{source}: non-finite positions in the first frame")
    keep = int(np.argmin(finite)) if not finite.all() else t
    return keep, (f"non-finite from frame {keep}: shown up to frame {keep - 1}" if keep < t else "")


def _geometry(r: Rollout) -> Geometry:
    layers = int(r.layer_index.max()) + 1 if r.layer_index.size else 1
    face_layer = r.layer_index[r.faces[:, 0]]
    layer_vertices, layer_faces = [], []
    for k in range(layers):
        idx = np.flatnonzero(r.layer_index == k)
        remap = np.full(r.num_vertices, -1, np.int64)
        remap[idx] = np.arange(len(idx))
        f = remap[r.faces[face_layer == k]]
        layer_vertices.append(idx)
        layer_faces.append(f[(f >= 0).all(axis=1)])  # a face across two layers is dropped
    return Geometry(layer_vertices, layer_faces, r.body_faces.astype(np.int64), r.garment_positions[0],
                    r.body_vertices[0])


def _frames(r: Rollout, count: int) -> list[RolloutFrame]:
    out = []
    for t in range(count):
        m = {k: float(x) for k, x in zip(r.metric_names, r.metrics[t], strict=True) if np.isfinite(x)}
        a = r.repulsion_acceleration[t]
        if "repulsion_mean" not in m:
            mag = np.linalg.norm(a, axis=1)
            m["repulsion_mean"], m["repulsion_max"] = float(mag.mean()), float(mag.max(initial=0.0))
        out.append(RolloutFrame(int(r.frame_index[t]) if t < len(r.frame_index) else t, r.garment_positions[t],
                                r.body_vertices[t], np.zeros_like(a), a, r.layer_penetration[t],
                                r.body_penetration[t], m, False))
    return out


def load_extra(source: str | Path | bytes, key: str, name: str | None = None) -> ExtraRollout:
    """Load and validate a saved rollout.

    Args:
        source: NPZ path or its bytes (an upload); key: the variant key to give it; name: file name for messages.

    Raises:
        ExtraRolloutError: unreadable, too large, missing or inconsistent arrays, non-finite first frame.
    """
    label = name or (str(source) if not isinstance(source, bytes) else "upload")
    if isinstance(source, bytes):
        data: bytes | Path = source
    else:
        data = Path(source)
        if not data.is_file():
            raise ExtraRolloutError(f"{label}: no such file")
    _check_size(data, label)
    try:
        r = load_rollout_npz(io.BytesIO(data) if isinstance(data, bytes) else data)
    except ExportError as exc:
        raise ExtraRolloutError(f"{label}: {str(exc).split(': ', 1)[-1]}") from exc
    except Exception as exc:  # noqa: BLE001 - any other decoding failure is a bad file too
        raise ExtraRolloutError(f"{label}: not a rollout NPZ ({type(exc).__name__}: {exc})") from exc
    if not isinstance(r.meta, dict):
        raise ExtraRolloutError(f"{label}: meta is not a JSON object")
    keep, note = _validate(r, label)
    scene = tuple(str(r.meta[k]) if r.meta.get(k) is not None else None for k in SCENE_KEYS)
    return ExtraRollout(key, _label(r.meta, label), Path(label).name, r, _frames(r, keep), _geometry(r),
                        scene, note)  # type: ignore[arg-type]


class ExtraStore:
    """The saved rollouts of one viewer (thread-safe), in the order they were added."""

    def __init__(self) -> None:
        self._items: dict[str, ExtraRollout] = {}
        self._count = 0
        self._lock = threading.Lock()

    def add(self, source: str | Path | bytes | IO[bytes], name: str | None = None) -> ExtraRollout:
        """Validate and keep a rollout (a path or, for uploads, bytes); returns it.

        Raises:
            ExtraRolloutError: see :func:`load_extra`; also when :data:`MAX_EXTRAS` are held already.
        """
        if not isinstance(source, str | Path | bytes):
            source = source.read()
        if isinstance(source, bytes) and len(source) > MAX_ROLLOUT_UPLOAD_BYTES:
            raise ExtraRolloutError(f"{name or 'upload'}: {len(source) / 1e6:.1f} MB is over the "
                                    f"{MAX_ROLLOUT_UPLOAD_BYTES / 2**20:.0f} MB limit for rollout uploads")
        with self._lock:
            if len(self._items) >= MAX_EXTRAS:
                raise ExtraRolloutError(f"{name or source}: at most {MAX_EXTRAS} saved rollouts per viewer")
            self._count += 1
            key = f"{EXTRA_PREFIX}{self._count}"
        extra = load_extra(source, key, name)  # type: ignore[arg-type]
        labels = {e.label for e in self._items.values()}
        if extra.label in labels:  # two files with the same meta variant: tell them apart (clip, else file)
            options = [f"{extra.label} · {extra.scene[1]}"] if extra.scene[1] else []
            options.append(f"{extra.label} · {Path(extra.source).stem}"[:80])
            extra.label = next((o for o in options if o not in labels), f"{options[-1]} ({key})")
        with self._lock:
            self._items[key] = extra
        return extra

    def get(self, key: str) -> ExtraRollout | None:
        return self._items.get(key)

    def keys(self) -> list[str]:
        return list(self._items)

    def items(self) -> list[ExtraRollout]:
        return list(self._items.values())

    def __contains__(self, key: object) -> bool:
        return key in self._items

    def __len__(self) -> int:
        return len(self._items)


def is_extra(variant: str) -> bool:
    return variant.startswith(EXTRA_PREFIX)


__all__ = ["EXTRA_PREFIX", "MAX_ROLLOUT_UPLOAD_BYTES", "ExtraRollout", "ExtraRolloutError", "ExtraStore",
           "Geometry", "is_extra", "load_extra"]
