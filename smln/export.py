"""Rollout files: the NPZ every tool shares, and conversions to OBJ sequences, PC2 point caches and GLB.

The rollout NPZ (written by :func:`save_rollout_npz`, read by :func:`load_rollout_npz`) holds, for T frames of a
cloth with V vertices in :class:`~smln.cloth.Cloth` order and a body with Vb vertices:

==========================  ==================  ==========================================================
key                         shape / dtype       meaning
==========================  ==================  ==========================================================
``garment_positions``       (T, V, 3) float32   cloth vertices, meters (Z up)
``layer_index``             (V,) int32          0 = innermost layer
``faces``                   (F, 3) int32        cloth triangles into the concatenated vertices
``body_vertices``           (T, Vb, 3) float32  posed body, meters
``body_faces``              (Fb, 3) int32       body triangles
``repulsion_acceleration``  (T, V, 3) float32   repulsion-layer acceleration a, meters/frame^2
``layer_penetration``       (T, V) bool         vertex behind the layer beneath it
``body_penetration``        (T, V) bool         vertex inside the body
``frame_index``             (T,) int32          frame number in the clip
``metric_names``            (M,) str            per-frame metric keys
``metrics``                 (T, M) float32      per-frame metrics (NaN where a frame lacks a key)
``layer_names``             (L,) str            garment names, inner -> outer
``fps``                     () float32          frames per second (30)
``meta``                    () str              JSON: outfit, clip, shape, variant, ...
==========================  ==================  ==========================================================

Exports (:func:`write_obj_zip`, :func:`write_pc2`, :func:`write_glb_zip`) take a :class:`Rollout`.
GLB export is **one static GLB per frame in a zip** (trimesh has no clean morph-target animation writer);
the PC2 cache plus one OBJ is the route to an animated mesh in Blender (Mesh Cache modifier).
"""

from __future__ import annotations

import argparse
import io
import json
import struct
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

PC2_HEADER = struct.Struct("<12siiffi")
"""Blender's PC2 header: signature, version, num points, start frame, sample rate, num samples."""
PC2_SIGNATURE = b"POINTCACHE2\0"

LAYER_COLOURS = np.array(
    [[70, 130, 220, 255], [230, 150, 60, 255], [90, 180, 110, 255], [180, 90, 200, 255]], dtype=np.uint8
)
"""RGBA colour per layer (inner -> outer, cycled) in GLB exports."""
BODY_COLOUR = np.array([200, 200, 200, 255], dtype=np.uint8)


class ExportError(ValueError):
    """A rollout file that cannot be read or converted."""


@dataclass
class Rollout:
    """A rollout in memory (see the module docstring for shapes and units)."""

    garment_positions: np.ndarray
    layer_index: np.ndarray
    faces: np.ndarray
    body_vertices: np.ndarray
    body_faces: np.ndarray
    repulsion_acceleration: np.ndarray
    layer_penetration: np.ndarray
    body_penetration: np.ndarray
    frame_index: np.ndarray
    metric_names: list[str]
    metrics: np.ndarray
    layer_names: list[str] = field(default_factory=list)
    fps: float = 30.0
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.garment_positions.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.garment_positions.shape[1])

    def metric(self, name: str) -> np.ndarray:
        """(T,) float32 values of one per-frame metric (NaN where missing)."""
        if name not in self.metric_names:
            return np.full(self.num_frames, np.nan, dtype=np.float32)
        return self.metrics[:, self.metric_names.index(name)]


def _np(a: Any, dtype: Any) -> np.ndarray:
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a, dtype=dtype)


def rollout_from_frames(
    frames: Sequence[Any],
    faces: Any,
    layer_index: Any,
    body_faces: Any,
    layer_names: Sequence[str] = (),
    fps: float = 30.0,
    meta: dict[str, Any] | None = None,
) -> Rollout:
    """Stack :class:`smln.rollout.RolloutFrame` objects into a :class:`Rollout`.

    Args:
        frames: T rollout frames (``garment_positions (V, 3)``, ``body_vertices (Vb, 3)``, ...), T >= 1.
        faces: (F, 3) cloth faces; layer_index: (V,) layer per vertex; body_faces: (Fb, 3).
        layer_names: garment names inner -> outer; fps: frames per second; meta: free JSON-able description.
    """
    if len(frames) == 0:
        raise ExportError("no frames to export")
    names: list[str] = []
    for f in frames:
        names.extend(k for k in f.metrics if k not in names)
    metrics = np.array(
        [[float(f.metrics.get(k, np.nan)) for k in names] for f in frames], dtype=np.float32
    ).reshape(len(frames), len(names))
    return Rollout(
        garment_positions=np.stack([_np(f.garment_positions, np.float32) for f in frames]),
        layer_index=_np(layer_index, np.int32),
        faces=_np(faces, np.int32),
        body_vertices=np.stack([_np(f.body_vertices, np.float32) for f in frames]),
        body_faces=_np(body_faces, np.int32),
        repulsion_acceleration=np.stack([_np(f.repulsion_acceleration, np.float32) for f in frames]),
        layer_penetration=np.stack([_np(f.layer_penetration, bool) for f in frames]),
        body_penetration=np.stack([_np(f.body_penetration, bool) for f in frames]),
        frame_index=np.array([int(f.index) for f in frames], dtype=np.int32),
        metric_names=names,
        metrics=metrics,
        layer_names=list(layer_names),
        fps=float(fps),
        meta=dict(meta or {}),
    )


def save_rollout_npz(
    path: str | Path | IO[bytes],
    frames: Sequence[Any] | Rollout,
    cloth: Any = None,
    body_faces: Any = None,
    meta: dict[str, Any] | None = None,
) -> Rollout:
    """Write a rollout NPZ (compressed).

    Args:
        path: file path or binary file object.
        frames: T :class:`smln.rollout.RolloutFrame` objects, or an already stacked :class:`Rollout`.
        cloth: the :class:`smln.cloth.Cloth` the frames animate (faces, layer index, layer names); unused for a
            :class:`Rollout`.
        body_faces: (Fb, 3) body faces; unused for a :class:`Rollout`.
        meta: JSON-able description (outfit, clip, shape, variant ...) stored under ``meta``.

    Returns:
        The :class:`Rollout` written.
    """
    if isinstance(frames, Rollout):
        r = frames
        if meta:
            r.meta.update(meta)
    else:
        if cloth is None or body_faces is None:
            raise ExportError("save_rollout_npz needs the cloth and the body faces with a list of frames")
        r = rollout_from_frames(frames, cloth.faces, cloth.layer_index, body_faces, cloth.layer_names, meta=meta)
    np.savez_compressed(
        path,
        garment_positions=r.garment_positions,
        layer_index=r.layer_index,
        faces=r.faces,
        body_vertices=r.body_vertices,
        body_faces=r.body_faces,
        repulsion_acceleration=r.repulsion_acceleration,
        layer_penetration=r.layer_penetration,
        body_penetration=r.body_penetration,
        frame_index=r.frame_index,
        metric_names=np.array(r.metric_names, dtype=str),
        metrics=r.metrics,
        layer_names=np.array(r.layer_names, dtype=str),
        fps=np.float32(r.fps),
        meta=np.array(json.dumps(r.meta)),
    )
    return r


REQUIRED_KEYS = ("garment_positions", "layer_index", "faces", "body_vertices", "body_faces")


def load_rollout_npz(path: str | Path | IO[bytes]) -> Rollout:
    """Read a rollout NPZ written by :func:`save_rollout_npz` (missing optional arrays are filled in).

    Raises:
        ExportError: the file is not a readable NPZ or lacks the required arrays / has inconsistent shapes.
    """
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ExportError(f"{path}: not a rollout NPZ ({str(exc) or type(exc).__name__})") from exc
    try:
        r = _read_arrays(data, path)
    except ExportError:
        raise
    except (ValueError, TypeError, KeyError, OverflowError, EOFError, OSError, zipfile.BadZipFile) as exc:
        first = str(exc).strip().splitlines()[0][:120] if str(exc).strip() else ""
        raise ExportError(f"{path}: not a rollout NPZ ({type(exc).__name__}: {first})") from None
    _check_shapes(r, path)
    return r


def _read_arrays(data: Any, path: Any) -> Rollout:
    """The arrays of an open NPZ as a :class:`Rollout` (conversion errors propagate)."""
    with data:
        missing = [k for k in REQUIRED_KEYS if k not in data.files]
        if missing:
            raise ExportError(f"{path}: missing arrays {', '.join(missing)} (not a rollout NPZ?)")
        x = np.asarray(data["garment_positions"], dtype=np.float32)
        if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] == 0:
            raise ExportError(f"{path}: garment_positions must be (T, V, 3) with T >= 1, got {x.shape}")
        t, v = x.shape[:2]

        def get(key: str, default: np.ndarray) -> np.ndarray:
            return data[key] if key in data.files else default

        r = Rollout(
            garment_positions=x,
            layer_index=np.asarray(data["layer_index"], dtype=np.int32),
            faces=np.asarray(data["faces"], dtype=np.int32),
            body_vertices=np.asarray(data["body_vertices"], dtype=np.float32),
            body_faces=np.asarray(data["body_faces"], dtype=np.int32),
            repulsion_acceleration=np.asarray(get("repulsion_acceleration", np.zeros_like(x)), dtype=np.float32),
            layer_penetration=np.asarray(get("layer_penetration", np.zeros((t, v), bool)), dtype=bool),
            body_penetration=np.asarray(get("body_penetration", np.zeros((t, v), bool)), dtype=bool),
            frame_index=np.asarray(get("frame_index", np.arange(t)), dtype=np.int32),
            metric_names=[str(s) for s in get("metric_names", np.zeros(0, dtype=str))],
            metrics=np.asarray(get("metrics", np.zeros((t, 0))), dtype=np.float32),
            layer_names=[str(s) for s in get("layer_names", np.zeros(0, dtype=str))],
            fps=float(get("fps", np.float32(30.0))),
            meta=json.loads(str(get("meta", np.array("{}")))),
        )
    return r


def _check_shapes(r: Rollout, path: Any) -> None:
    """Every array's shape against (T, V) and the index ranges; :class:`ExportError` names the first problem."""
    t, v = r.garment_positions.shape[:2]
    bv = r.body_vertices
    if r.layer_index.shape != (v,) or bv.ndim != 3 or bv.shape[0] != t or bv.shape[2] != 3:
        raise ExportError(f"{path}: inconsistent shapes (layer_index {r.layer_index.shape}, V = {v}, "
                          f"body_vertices {bv.shape}, T = {t})")
    for name, faces, n in (("faces", r.faces, v), ("body_faces", r.body_faces, bv.shape[1])):
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ExportError(f"{path}: {name} {faces.shape} is not (F, 3)")
        if faces.size and (faces.min() < 0 or faces.max() >= n):
            raise ExportError(f"{path}: {name} index outside the {n} vertices")
    if r.layer_index.size and (r.layer_index.min() < 0 or r.layer_index.max() >= 64):
        raise ExportError(f"{path}: layer_index outside 0..63")
    expected = {"repulsion_acceleration": (t, v, 3), "layer_penetration": (t, v), "body_penetration": (t, v),
                "frame_index": (t,), "metrics": (t, len(r.metric_names))}
    for name, shape in expected.items():
        if getattr(r, name).shape != shape:
            raise ExportError(f"{path}: {name} {getattr(r, name).shape} is not {shape}")
    if not isinstance(r.meta, dict) or not np.isfinite(r.fps) or r.fps <= 0:
        raise ExportError(f"{path}: meta must be a JSON object and fps positive (fps {r.fps})")


def _obj_text(vertices: np.ndarray, faces: np.ndarray, groups: Iterable[tuple[str, np.ndarray]] = ()) -> str:
    """OBJ text of one mesh; ``groups`` are (name, face mask) pairs written as ``g`` blocks."""
    buf = io.StringIO()
    buf.write("# SMLN rollout frame (meters, Z up)\n")
    np.savetxt(buf, vertices, fmt="v %.6f %.6f %.6f")
    groups = list(groups) or [("mesh", np.ones(len(faces), dtype=bool))]
    for name, mask in groups:
        buf.write(f"g {name}\n")
        np.savetxt(buf, faces[mask] + 1, fmt="f %d %d %d")
    return buf.getvalue()


def _layer_groups(r: Rollout) -> list[tuple[str, np.ndarray]]:
    face_layer = r.layer_index[r.faces[:, 0]] if len(r.faces) else np.zeros(0, np.int32)
    count = int(r.layer_index.max()) + 1 if r.layer_index.size else 0
    names = [r.layer_names[k] if k < len(r.layer_names) else f"layer_{k}" for k in range(count)]
    return [(f"{k}_{names[k]}", face_layer == k) for k in range(count)]


def write_obj_zip(r: Rollout, out: str | Path | IO[bytes], include_body: bool = False) -> None:
    """One OBJ per frame (``garment_0000.obj`` ..., a ``g`` group per layer) in a zip.

    Args:
        r: the rollout; out: zip path or binary file object;
        include_body: also write ``body_0000.obj`` ... with the posed body.
    """
    groups = _layer_groups(r)
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for t in range(r.num_frames):  # one file per frame
            zf.writestr(f"garment_{t:04d}.obj", _obj_text(r.garment_positions[t], r.faces, groups))
            if include_body:
                zf.writestr(f"body_{t:04d}.obj", _obj_text(r.body_vertices[t], r.body_faces))


def pc2_bytes(positions: np.ndarray, start_frame: float = 0.0, sample_rate: float = 1.0) -> bytes:
    """Blender PC2 point cache of (T, N, 3) positions: the header then float32 xyz per sample, little-endian."""
    positions = np.ascontiguousarray(positions, dtype="<f4")
    if positions.ndim != 3 or positions.shape[2] != 3:
        raise ExportError(f"PC2 needs (T, N, 3) positions, got {positions.shape}")
    t, n = positions.shape[:2]
    return PC2_HEADER.pack(PC2_SIGNATURE, 1, n, float(start_frame), float(sample_rate), t) + positions.tobytes()


def write_pc2(r: Rollout, out: str | Path | IO[bytes], start_frame: float = 0.0) -> None:
    """The garment as a PC2 point cache (one sample per frame). Pair it with the frame-0 OBJ in Blender."""
    data = pc2_bytes(r.garment_positions, start_frame=start_frame, sample_rate=1.0)
    if isinstance(out, (str, Path)):
        Path(out).write_bytes(data)
    else:
        out.write(data)


def read_pc2(data: bytes) -> tuple[dict[str, float], np.ndarray]:
    """Parse PC2 bytes into (header dict, (T, N, 3) float32 positions)."""
    sig, version, n, start, rate, t = PC2_HEADER.unpack_from(data)
    if sig != PC2_SIGNATURE:
        raise ExportError("not a PC2 file (bad signature)")
    pos = np.frombuffer(data, dtype="<f4", offset=PC2_HEADER.size, count=t * n * 3).reshape(t, n, 3)
    return {"version": version, "num_points": n, "start_frame": start, "sample_rate": rate, "num_samples": t}, pos


def frame_glb(r: Rollout, t: int, include_body: bool = True) -> bytes:
    """One frame as a GLB: a node per garment layer (coloured) and the body."""
    import trimesh

    scene = trimesh.Scene()
    x = r.garment_positions[t]
    for k, (name, mask) in enumerate(_layer_groups(r)):
        faces = r.faces[mask]
        used = np.unique(faces)
        remap = np.full(len(x), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        mesh = trimesh.Trimesh(x[used], remap[faces], process=False)
        mesh.visual.face_colors = LAYER_COLOURS[k % len(LAYER_COLOURS)]
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    if include_body:
        body = trimesh.Trimesh(r.body_vertices[t], r.body_faces, process=False)
        body.visual.face_colors = BODY_COLOUR
        scene.add_geometry(body, node_name="body", geom_name="body")
    return scene.export(file_type="glb")


def write_glb_zip(r: Rollout, out: str | Path | IO[bytes], include_body: bool = True) -> None:
    """One static GLB per frame (``frame_0000.glb`` ...) in a zip (see the module docstring)."""
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as zf:
        for t in range(r.num_frames):
            zf.writestr(f"frame_{t:04d}.glb", frame_glb(r, t, include_body))


def export_bytes(r: Rollout, fmt: str, include_body: bool = False) -> tuple[str, bytes]:
    """The rollout in ``fmt`` (``npz``, ``obj``, ``pc2``, ``glb``) as (file suffix, bytes) for downloads."""
    buf = io.BytesIO()
    if fmt == "npz":
        save_rollout_npz(buf, r)
        return ".npz", buf.getvalue()
    if fmt == "obj":
        write_obj_zip(r, buf, include_body=include_body)
        return "_obj.zip", buf.getvalue()
    if fmt == "pc2":
        write_pc2(r, buf)
        return ".pc2", buf.getvalue()
    if fmt == "glb":
        write_glb_zip(r, buf, include_body=include_body)
        return "_glb.zip", buf.getvalue()
    raise ExportError(f"unknown export format {fmt!r}: use npz, obj, pc2 or glb")


def cli_main(args: argparse.Namespace) -> None:
    """``smln export ROLLOUT.npz --format obj|pc2|glb --out PATH [--with-body] [--force]``."""
    parser = argparse.ArgumentParser(prog="smln export", description="convert a rollout NPZ")
    parser.add_argument("rollout", help="rollout NPZ (from `smln rollout` or the viewer)")
    parser.add_argument("--format", required=True, choices=["obj", "pc2", "glb"],
                        help="obj: zip of one OBJ per frame; pc2: Blender point cache; glb: zip of one GLB per frame")
    parser.add_argument("--out", required=True, help="output path")
    parser.add_argument("--with-body", action="store_true", help="also write the body (obj, glb)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing file")
    ns = parser.parse_args(getattr(args, "argv", []))
    out = Path(ns.out)
    if out.exists() and not ns.force:
        raise FileExistsError(f"{out} exists; pass --force to overwrite it")
    r = load_rollout_npz(ns.rollout)
    _, data = export_bytes(r, ns.format, include_body=ns.with_body)
    out.write_bytes(data)
    print(f"wrote {out}: {r.num_frames} frames, {r.num_vertices} garment vertices ({ns.format})")
