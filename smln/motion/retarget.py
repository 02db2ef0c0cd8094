"""Retargeting CMU-skeleton BVH clips onto the body's ``cmu_mb`` rig.

Route (verified in DESIGN.md): world joint rotations from the BVH, changed from BVH axes (Y up, +Z forward) to the
body's (Z up, facing -Y) by ``A``, composed with a per-bone rest correction and the body's T-pose orientation:

    D_b(t) = A G_b(t) A^T  C_b  D_T,b

``C_b`` is the minimal rotation taking the body's T-pose bone axis onto the BVH zero-pose bone direction (found
along the first-child chain, since several CMU joints have zero length). Hips, the hip joints and the clavicles
are not corrected (their BVH directions are proportion artefacts). The root follows the BVH's mid-hip point,
scaled by the leg-length ratio of body and subject.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smln.body.model import BONE_AXIS, Body, _min_rotation
from smln.body.skinning import world_orient_fk
from smln.cloth import FPS
from smln.motion.bvh import BvhClip, MotionError
from smln.motion.resample import slerp_rotations

BVH_TO_BODY = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Axis change A from BVH (Y up, +Z forward) to the body frame (Z up, facing -Y)."""

NAME_ALIASES = {"LeftHandIndex1": "LeftHandFinger1", "RightHandIndex1": "RightHandFinger1"}
"""BVH joint name -> body bone name where the two differ."""

REQUIRED_JOINTS = (
    "Hips", "LeftUpLeg", "LeftLeg", "LeftFoot", "RightUpLeg", "RightLeg", "RightFoot",
    "Spine", "Neck", "Head", "LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand",
)
"""Joints a clip must have; the other body bones follow their parent when the clip lacks them."""

UNCORRECTED = {"Hips", "LHipJoint", "RHipJoint", "LeftShoulder", "RightShoulder"}


@dataclass
class Motion:
    """A clip retargeted to one body, at the simulation rate.

    Attributes:
        name: clip name.
        world_orientations: (T, B, 3, 3) float32 world bone orientations on the body rig.
        root_positions: (T, 3) float32 root-bone head positions, meters (before floor alignment).
        fps: frames per second (30).
        leg_scale: body leg length / BVH subject leg length, used for the root translation.
    """

    name: str
    world_orientations: torch.Tensor
    root_positions: torch.Tensor
    fps: float
    leg_scale: float

    @property
    def num_frames(self) -> int:
        return int(self.world_orientations.shape[0])


def _bone_direction(clip: BvhClip, joint: int) -> np.ndarray | None:
    """BVH zero-pose direction of the bone at ``joint``: the first non-zero offset down the first-child chain."""
    children = [[c for c, p in enumerate(clip.parents) if p == j] for j in range(len(clip.parents))]
    j = joint
    for _ in range(len(clip.parents)):
        if not children[j]:
            end = clip.end_offsets[j]
            return end if np.linalg.norm(end) > 1e-6 else None
        c = children[j][0]
        if np.linalg.norm(clip.offsets[c]) > 1e-6:
            return clip.offsets[c]
        j = c
    return None


def _leg_length(points_upleg: np.ndarray, points_leg: np.ndarray, points_foot: np.ndarray) -> float:
    return float(np.linalg.norm(points_leg - points_upleg) + np.linalg.norm(points_foot - points_leg))


def retarget(clip: BvhClip, body: Body, fps: float = FPS) -> Motion:
    """Retarget a parsed CMU-skeleton clip onto ``body`` and resample it to ``fps``.

    Raises:
        MotionError: when the clip lacks joints the body rig needs.
    """
    bvh_index = {NAME_ALIASES.get(n, n): i for i, n in enumerate(clip.joint_names)}
    missing = [n for n in REQUIRED_JOINTS if n not in bvh_index]
    if missing:
        unknown = [n for n in clip.joint_names if NAME_ALIASES.get(n, n) not in body.bone_names]
        raise MotionError(
            f"{clip.name}: skeleton does not match the CMU rig: missing joints {', '.join(missing)}"
            + (f"; unknown joints {', '.join(unknown[:6])}" if unknown else "")
        )

    rotations, root = slerp_rotations(clip.local_rotations, clip.root_positions, clip.fps, fps)
    sub = BvhClip(clip.name, clip.joint_names, clip.parents, clip.offsets, clip.end_offsets, rotations, root, fps)
    world = sub.world_rotations()  # (T, J, 3, 3)
    joints = sub.joint_positions(world)  # (T, J, 3) meters, BVH axes
    a = BVH_TO_BODY
    world_body = np.einsum("ik,tjkl,ml->tjim", a, world, a)  # A G A^T

    tpose = body.tpose_orientations.double().numpy()
    num_frames, num_bones = world.shape[0], body.num_bones
    orient = np.empty((num_frames, num_bones, 3, 3))
    for b, name in enumerate(body.bone_names):
        if name in bvh_index:
            j = bvh_index[name]
            corr = np.eye(3)
            direction = _bone_direction(clip, j)
            if name not in UNCORRECTED and direction is not None:
                corr = _min_rotation(tpose[b] @ BONE_AXIS, a @ direction)
            orient[:, b] = world_body[:, j] @ (corr @ tpose[b])
        else:  # follow the parent rigidly from the T-pose
            p = body.bone_parents[b]
            rel = tpose[p].T @ tpose[b]
            orient[:, b] = orient[:, p] @ rel

    # Root: follow the BVH mid-hip point scaled by the leg-length ratio.
    li, ri = bvh_index["LeftUpLeg"], bvh_index["RightUpLeg"]
    bvh_leg = float(
        np.linalg.norm(clip.offsets[bvh_index["LeftLeg"]]) + np.linalg.norm(clip.offsets[bvh_index["LeftFoot"]])
    )
    heads = body.bone_heads.double().numpy()
    body_leg = _leg_length(
        heads[body.bone_index("LeftUpLeg")], heads[body.bone_index("LeftLeg")], heads[body.bone_index("LeftFoot")]
    )
    scale = body_leg / bvh_leg
    mid_bvh = 0.5 * (joints[:, li] + joints[:, ri]) @ a.T * scale  # (T, 3) body axes
    mid_bvh[:, :2] -= mid_bvh[0, :2]  # start above the origin

    orient_t = torch.from_numpy(orient).float()
    rest_root = body.root_position.double()
    tf = world_orient_fk(
        body.rest_bone_poses.double(), body.bone_parents, torch.from_numpy(orient), rest_root.expand(num_frames, 3)
    )
    hl, hr = body.bone_index("LeftUpLeg"), body.bone_index("RightUpLeg")
    heads_t = torch.from_numpy(heads)
    mid_body = 0.5 * (
        (tf[:, hl, :, :3] @ heads_t[hl] + tf[:, hl, :, 3]) + (tf[:, hr, :, :3] @ heads_t[hr] + tf[:, hr, :, 3])
    )
    root_positions = rest_root + (torch.from_numpy(mid_bvh) - mid_body)
    return Motion(
        name=clip.name, world_orientations=orient_t, root_positions=root_positions.float(), fps=fps, leg_scale=scale
    )


def posed_bone_ends(body: Body, motion: Motion) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, B, 3) posed bone heads and tails of the body along ``motion`` (before floor alignment), meters."""
    tf = world_orient_fk(body.rest_bone_poses, body.bone_parents, motion.world_orientations, motion.root_positions)

    def apply(points: torch.Tensor) -> torch.Tensor:
        return torch.einsum("tbij,bj->tbi", tf[..., :3], points) + tf[..., 3]

    return apply(body.bone_heads), apply(body.bone_tails)
