"""Uploaded BVH clips and OBJ garments: size limits, validation through the library, a private upload folder.

An upload is accepted only if the library loads it (``smln.motion.load_body_sequence`` for a clip,
``smln.garments.Garment.from_obj`` for a garment); otherwise :class:`UploadError` says why in one line and
nothing is kept. Accepted files get keys ``upload:bvh:<n>`` / ``upload:obj:<n>`` that the catalog resolves.
"""

from __future__ import annotations

import re
import shutil
import tempfile
import threading
from pathlib import Path

from smln.body import load_body
from smln.cloth import Cloth

MAX_BVH_BYTES = 8 * 1024 * 1024
"""Largest accepted BVH upload (8 MB, about a minute of 120 fps CMU motion)."""
MAX_OBJ_BYTES = 16 * 1024 * 1024
"""Largest accepted OBJ upload (16 MB); the garment importer also caps the vertex count."""


class UploadError(ValueError):
    """An upload was refused; the message says why."""


def _clean_name(name: str) -> str:
    stem = Path(name).name
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", stem)[:80] or "upload"


class UploadStore:
    """Validated uploads of this viewer session (files live in a private temporary folder).

    Args:
        directory: where accepted files are written (default: a fresh temporary folder, removed by
            :meth:`close`).
    """

    def __init__(self, directory: str | Path | None = None) -> None:
        self._own = directory is None
        self.directory = Path(directory or tempfile.mkdtemp(prefix="smln-viewer-uploads-"))
        self.directory.mkdir(parents=True, exist_ok=True)
        self._clips: dict[str, tuple[str, Path]] = {}
        self._garments: dict[str, tuple[str, Path]] = {}
        self._cloths: dict[tuple[str, str], Cloth] = {}
        self._notes: dict[str, str] = {}
        self._lock = threading.Lock()
        self._count = 0

    def _write(self, kind: str, name: str, content: bytes, limit: int, suffix: str) -> tuple[str, Path]:
        if not name.lower().endswith(suffix):
            raise UploadError(f"{name}: expected a {suffix} file")
        if len(content) == 0:
            raise UploadError(f"{name}: the file is empty")
        if len(content) > limit:
            raise UploadError(f"{name}: {len(content) / 1e6:.1f} MB is over the {limit / 2**20:.0f} MB limit "
                              f"for {suffix} uploads")
        with self._lock:
            self._count += 1
            key = f"upload:{kind}:{self._count}"
        path = self.directory / f"{self._count:03d}_{_clean_name(name)}"
        path.write_bytes(content)
        return key, path

    def add_bvh(self, name: str, content: bytes, shape: str) -> str:
        """Validate and keep a BVH clip (parsed and retargeted onto ``shape``); returns its key.

        Raises:
            UploadError: wrong extension, empty, too large, or rejected by the motion loader.
        """
        from smln.motion import load_body_sequence

        key, path = self._write("bvh", name, content, MAX_BVH_BYTES, ".bvh")
        try:
            seq = load_body_sequence(path, load_body(shape))
            if seq.num_frames < 3:
                raise UploadError(f"{name}: only {seq.num_frames} frames at 30 fps; a rollout needs at least 3")
        except Exception as exc:
            path.unlink(missing_ok=True)
            raise UploadError(_one_line(exc, name)) from exc
        with self._lock:
            self._clips[key] = (Path(name).stem, path)
        return key

    def add_obj(self, name: str, content: bytes, shape: str) -> str:
        """Validate and keep an OBJ garment (fitted to ``shape`` by the garment importer); returns its key.

        Raises:
            UploadError: wrong extension, empty, too large, or rejected by the garment importer.
        """
        key, path = self._write("obj", name, content, MAX_OBJ_BYTES, ".obj")
        label = Path(name).stem
        try:
            cloth, note = self._make_cloth(label, path, shape)
        except Exception as exc:
            path.unlink(missing_ok=True)
            raise UploadError(_one_line(exc, name)) from exc
        with self._lock:
            self._garments[key] = (label, path)
            self._notes[key] = note
            self._cloths[(key, shape)] = cloth
        return key

    @staticmethod
    def _make_cloth(label: str, path: Path, shape: str) -> tuple[Cloth, str]:
        """The garment as a one-layer cloth on ``shape``, and how its file was read (unit, up axis; "" as is)."""
        from smln.garments.garment import Garment
        from smln.garments.outfit import Outfit

        garment = Garment.from_obj(path, load_body(shape))
        return Outfit(label, [garment], shape).to_cloth(), garment.note

    def clips(self) -> list[tuple[str, str]]:
        """(key, label) of the accepted clips."""
        return [(k, label) for k, (label, _) in self._clips.items()]

    def garments(self) -> list[tuple[str, str]]:
        """(key, label) of the accepted garments."""
        return [(k, label) for k, (label, _) in self._garments.items()]

    def clip_path(self, key: str) -> Path:
        if key not in self._clips:
            raise UploadError(f"unknown uploaded clip {key!r}")
        return self._clips[key][1]

    def note(self, key: str) -> str:
        """How the uploaded garment's file was read (``"read in cm, turned from Y up to Z up"``), "" if as is."""
        return self._notes.get(key, "")

    def cloth(self, key: str, shape: str) -> Cloth:
        """The uploaded garment as a one-layer cloth on ``shape`` (fitted once per shape)."""
        if key not in self._garments:
            raise UploadError(f"unknown uploaded garment {key!r}")
        with self._lock:
            cached = self._cloths.get((key, shape))
        if cached is None:
            label, path = self._garments[key]
            cached, _ = self._make_cloth(label, path, shape)
            with self._lock:
                self._cloths[(key, shape)] = cached
        return cached

    def close(self) -> None:
        """Remove the upload folder if this store created it."""
        if self._own:
            shutil.rmtree(self.directory, ignore_errors=True)


def _one_line(exc: BaseException, name: str) -> str:
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return msg if name in msg else f"{name}: {msg}"
