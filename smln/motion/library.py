"""The shipped CMU clips, their train/test split, and loading a clip onto a body in one call."""

from __future__ import annotations

import json
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
    """Path of a shipped clip by name, or of a user's .bvh file given as a path."""
    p = Path(name)
    if p.suffix.lower() == ".bvh":
        return p
    clip_split(name)
    return MOTION_DIR / f"{name}.bvh"


def load_motion(name_or_path: str | Path, body: Body) -> Motion:
    """Parse, retarget and resample a shipped clip (by name) or a user's BVH file (by path)."""
    return retarget(load_bvh(clip_path(str(name_or_path))), body)


def load_body_sequence(name_or_path: str | Path, body: Body, max_frames: int | None = None) -> BodySequence:
    """The posed body along a clip at 30 fps, feet on the floor; ``max_frames`` keeps only the first frames."""
    seq = pose_sequence(body, load_motion(name_or_path, body))
    return seq.slice(0, max_frames) if max_frames else seq
