"""The shipped CMU clips, their train/test split, and loading a clip onto a body in one call."""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import tempfile
import zlib
from functools import lru_cache
from pathlib import Path

from smln.body.model import Body
from smln.motion.bvh import MotionError, load_bvh
from smln.motion.posing import BodySequence, pose_sequence
from smln.motion.retarget import Motion, retarget

MOTION_DIR = Path(__file__).resolve().parent.parent / "data" / "motions"


@lru_cache(maxsize=1)
def manifest() -> list[dict]:
    """The clip manifest: one dict per shipped clip with ``name``, ``file``, ``kind`` and ``split`` (train/test)."""
    with open(MOTION_DIR / "manifest.json") as fh:
        return json.load(fh)["clips"]


def list_clips(split: str | None = None) -> list[str]:
    """Names of the shipped clips, optionally only one split (``"train"`` or ``"test"``)."""
    if split not in (None, "train", "test"):
        raise ValueError(f"unknown split {split!r}: use 'train' or 'test'")
    return [c["name"] for c in manifest() if split is None or c["split"] == split]


def clip_split(name: str) -> str:
    for c in manifest():
        if c["name"] == name:
            return c["split"]
    raise MotionError(f"unknown clip {name!r}; `smln motions` lists the shipped clips")


def clip_path(name: str) -> Path:
    """Path of a shipped clip by name (a plain .bvh file), or of a user's .bvh file given as a path.

    The shipped clips are stored gzip-compressed (``MOTION_DIR/NAME.bvh.gz``, a third of the size); the first use
    of one unpacks it into the cache (:func:`unpacked_clip`).
    """
    p = Path(name)
    if p.suffix.lower() == ".bvh":
        return p
    clip_split(name)
    packed = MOTION_DIR / f"{name}.bvh.gz"
    return unpacked_clip(packed) if packed.is_file() else MOTION_DIR / f"{name}.bvh"


def motion_cache_dir() -> Path:
    """Directory of unpacked shipped clips (``$SMLN_CACHE_DIR/motions`` or ``~/.cache/smln/motions``)."""
    root = os.environ.get("SMLN_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "smln") / "motions"


def unpacked_clip(gz_path: Path) -> Path:
    """The plain BVH of a gzip-compressed clip, unpacked once into :func:`motion_cache_dir` under a hash of the
    compressed bytes (an edited clip gets a fresh copy; a half-written one is never seen: written aside, then
    renamed). Falls back to a temporary directory when the cache is not writable.

    Raises:
        MotionError: the compressed file is missing or not gzip.
    """
    if not gz_path.is_file():
        raise MotionError(f"{gz_path.name}: no such file")
    packed = gz_path.read_bytes()
    name = gz_path.name.removesuffix(".gz")
    digest = hashlib.sha256(packed).hexdigest()[:12]
    for root in (motion_cache_dir(), Path(tempfile.gettempdir()) / "smln-motions"):
        target = root / digest / name
        if target.is_file():
            return target
        try:
            text = gzip.decompress(packed)
        except (OSError, EOFError, zlib.error) as exc:
            raise MotionError(f"{gz_path.name}: cannot unpack ({exc})") from None
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(text)
            tmp.replace(target)
            return target
        except OSError:
            continue
    raise MotionError(f"{gz_path.name}: no writable directory to unpack it into")


def load_motion(name_or_path: str | Path, body: Body) -> Motion:
    """Parse, retarget and resample a shipped clip (by name) or a user's BVH file (by path)."""
    return retarget(load_bvh(clip_path(str(name_or_path))), body)


def load_body_sequence(name_or_path: str | Path, body: Body, max_frames: int | None = None) -> BodySequence:
    """The posed body along a clip at 30 fps, feet on the floor; ``max_frames`` keeps only the first frames."""
    seq = pose_sequence(body, load_motion(name_or_path, body))
    return seq.slice(0, max_frames) if max_frames else seq
