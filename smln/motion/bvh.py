"""Reading BVH motion clips (parsed with the ``pybvh`` package) into validated numpy arrays.

Every failure is a :class:`MotionError` with a one-line message that names the file and what is wrong, never a
traceback from inside the parser.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

CMU_UNIT = 0.056444
"""Meters per CMU BVH unit ((1/0.45) inch, see smln/data/motions/README.md)."""

UNIT_CANDIDATES = {"m": 1.0, "cm": 0.01, "mm": 0.001, "inch": 0.0254}
"""Meters per file unit of other BVH sources (Mixamo writes cm, other exporters m, mm or inches)."""

PLAUSIBLE_EXTENT_M = (0.8, 2.6)
"""A human skeleton's zero pose spans this much, m (its largest bounding-box side: height or T-pose arm span)."""

TYPICAL_EXTENT_M = 1.6
"""The extent a unit is chosen for when the CMU unit gives an implausible skeleton, m."""

MAX_BVH_BYTES = 64 * 1024 * 1024
MAX_BVH_FRAMES = 120 * 60 * 10
"""Limits for user files: 64 MB and ten minutes at 120 fps."""


class MotionError(ValueError):
    """A motion clip that cannot be used, with a message meant for the user."""


@dataclass
class BvhClip:
    """A parsed BVH clip, in the file's own axes and in meters.

    Attributes:
        name: clip name (file stem).
        joint_names: J joint names, parents before children.
        parents: J parent indices (-1 for the root).
        offsets: (J, 3) float64 joint offsets from the parent, meters.
        end_offsets: (J, 3) float64 end-site offset of each joint (zeros where it has none), meters.
        local_rotations: (F, J, 3, 3) float64 local joint rotations per frame.
        root_positions: (F, 3) float64 root positions, meters.
        fps: frames per second of the file.
    """

    name: str
    joint_names: list[str]
    parents: list[int]
    offsets: np.ndarray
    end_offsets: np.ndarray
    local_rotations: np.ndarray
    root_positions: np.ndarray
    fps: float

    @property
    def num_frames(self) -> int:
        return int(self.local_rotations.shape[0])

    @property
    def duration(self) -> float:
        """Seconds covered by the frames (first to last sample)."""
        return (self.num_frames - 1) / self.fps

    def world_rotations(self) -> np.ndarray:
        """(F, J, 3, 3) world rotations of each joint (product of local rotations down the chain)."""
        world = np.empty_like(self.local_rotations)
        for j, p in enumerate(self.parents):
            world[:, j] = self.local_rotations[:, j] if p < 0 else world[:, p] @ self.local_rotations[:, j]
        return world

    def joint_positions(self, world: np.ndarray | None = None) -> np.ndarray:
        """(F, J, 3) world joint positions in meters (BVH forward kinematics)."""
        world = self.world_rotations() if world is None else world
        pos = np.empty(world.shape[:2] + (3,))
        for j, p in enumerate(self.parents):
            pos[:, j] = self.root_positions if p < 0 else pos[:, p] + world[:, p] @ self.offsets[j]
        return pos


START_WINDOW_S = 0.25
"""Only the first quarter second of a clip is searched for start-up glitches."""

MAX_START_STEP_DEG_PER_S = 1200.0
MAX_START_STEP_M_PER_S = 6.0
"""A frame-to-frame step faster than this (any joint's rotation, or the root's motion) near the start of a clip is
a converter artefact, not motion."""


def _trim_start(rotations: np.ndarray, root: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Drop the start-up glitches of a clip: the converter's reference pose (CMU frame 0), and in some CMU files
    a few more frozen or jumping frames before the motion proper (05_01: two, 07_12: a 2.4 m root jump,
    08_07: six frozen frames then a jump). The clip starts after the last implausibly fast step within the
    first :data:`START_WINDOW_S` seconds; clips without such a step are left as they are.

    Args:
        rotations: (F, J, 3, 3) local joint rotations; root: (F, 3) root positions, meters; fps: frame rate.
    """
    window = min(rotations.shape[0] - 1, max(1, int(round(START_WINDOW_S * fps))))
    if window < 1:
        return rotations, root
    rel = np.einsum("fjik,fjil->fjkl", rotations[:window], rotations[1 : window + 1])  # R_i^T R_{i+1}
    cos = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos)).max(axis=1) * fps  # deg/s, fastest joint per step
    speed = np.linalg.norm(root[1 : window + 1] - root[:window], axis=1) * fps  # m/s
    bad = np.nonzero((angle > MAX_START_STEP_DEG_PER_S) | (speed > MAX_START_STEP_M_PER_S))[0]
    if len(bad) == 0 or bad[-1] + 1 >= rotations.shape[0] - 1:
        return rotations, root
    first = bad[-1] + 1
    return rotations[first:], root[first:]


def zero_pose_extent(offsets: np.ndarray, parents: list[int]) -> float:
    """Largest side of the bounding box of the joints in the zero pose (all rotations identity), in the offsets'
    unit. ``offsets``: (J, 3) joint offsets from the parent; ``parents``: J parent indices, parents first."""
    pos = np.zeros_like(offsets)
    for j, p in enumerate(parents):  # J is a few dozen joints, once per file
        pos[j] = offsets[j] if p < 0 else pos[p] + offsets[j]
    return float((pos.max(axis=0) - pos.min(axis=0)).max())


def detect_unit(extent: float) -> float:
    """Meters per file unit for a skeleton whose zero pose spans ``extent`` file units.

    The CMU unit whenever it gives a human-sized skeleton (:data:`PLAUSIBLE_EXTENT_M`), so every CMU clip reads
    exactly as before; otherwise the unit of :data:`UNIT_CANDIDATES` whose skeleton is nearest (in ratio) to
    :data:`TYPICAL_EXTENT_M`. The retargeting itself is scale-free (the root follows the leg-length ratio); the
    unit matters for the start-up glitch test (m/s) and for the clip's reported positions.
    """
    low, high = PLAUSIBLE_EXTENT_M
    if extent <= 0 or low <= extent * CMU_UNIT <= high:
        return CMU_UNIT
    return min(UNIT_CANDIDATES.values(), key=lambda u: abs(np.log(extent * u / TYPICAL_EXTENT_M)))


def load_bvh(path: str | Path, unit: float | None = None, max_frames: int = MAX_BVH_FRAMES) -> BvhClip:
    """Parse and validate a BVH file.

    Args:
        path: the .bvh file.
        unit: meters per file unit; None (default) detects it from the skeleton's size (:func:`detect_unit`:
            the CMU unit 0.056444 for CMU files, cm for Mixamo, ...).
        max_frames: refuse longer files.

    Raises:
        MotionError: missing, empty, too large, not BVH, truncated, non-finite values, absurd frame counts.
    """
    path = Path(path)
    if not path.is_file():
        raise MotionError(f"{path.name}: no such file")
    size = path.stat().st_size
    if size == 0:
        raise MotionError(f"{path.name}: the file is empty")
    if size > MAX_BVH_BYTES:
        limit = MAX_BVH_BYTES // 2**20
        raise MotionError(f"{path.name}: {size / 1e6:.0f} MB is over the {limit} MB limit for BVH files")
    with open(path, "rb") as fh:
        head = fh.read(512)
    if b"\x00" in head or not head.lstrip().upper().startswith(b"HIERARCHY"):
        raise MotionError(f"{path.name}: not a BVH file (it must start with HIERARCHY)")
    declared = _declared_frames(path)
    if declared is not None and declared > max_frames:
        raise MotionError(f"{path.name}: {declared} frames is over the limit of {max_frames}")

    import pybvh

    try:
        bvh = pybvh.read_bvh_file(str(path))
        root, local = bvh.to_rotmat()
    except Exception as exc:  # the parser's own messages are precise but long: keep the first line
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MotionError(f"{path.name}: cannot parse BVH ({first[:200]})") from None

    names = list(bvh.joint_names)
    by_name = {n.name: n for n in bvh.nodes}
    nodes = [by_name[n] for n in names]
    parents = [names.index(n.parent.name) if n.parent is not None else -1 for n in nodes]
    offsets = np.array([n.offset for n in nodes], dtype=np.float64)
    end_offsets = np.zeros_like(offsets)
    for j, node in enumerate(nodes):
        ends = [c for c in node.children if c.is_end_site()]
        if ends:
            end_offsets[j] = np.asarray(ends[0].offset, dtype=np.float64)
    if not (np.isfinite(offsets).all() and np.isfinite(end_offsets).all()):
        raise MotionError(f"{path.name}: the skeleton has NaN or infinite joint offsets")
    if unit is None:
        unit = detect_unit(zero_pose_extent(offsets, parents))
    offsets, end_offsets = offsets * unit, end_offsets * unit

    if local.shape[0] == 0:
        raise MotionError(f"{path.name}: the file has no motion frames")
    if declared is not None and local.shape[0] != declared:
        raise MotionError(f"{path.name}: truncated: {local.shape[0]} frames of the {declared} declared")
    if not (np.isfinite(local).all() and np.isfinite(root).all()):
        raise MotionError(f"{path.name}: the motion contains NaN or infinite values")
    fps = float(bvh.fps)
    if not np.isfinite(fps) or fps <= 0 or fps > 1000:
        raise MotionError(f"{path.name}: implausible frame rate {fps}")
    local, root_m = _trim_start(local, root * unit, fps)
    return BvhClip(
        name=path.stem,
        joint_names=names,
        parents=parents,
        offsets=offsets,
        end_offsets=end_offsets,
        local_rotations=local,
        root_positions=root_m,
        fps=fps,
    )


def _declared_frames(path: Path) -> int | None:
    """The ``Frames:`` count of the MOTION header, read without parsing the data."""
    with open(path, "rb") as fh:
        for raw in fh:
            line = raw.strip()
            if line.upper().startswith(b"FRAMES:"):
                try:
                    return int(line.split(b":", 1)[1])
                except ValueError:
                    raise MotionError(f"{path.name}: unreadable frame count {line[:40]!r}") from None
    return None
