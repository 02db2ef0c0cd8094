"""Retargeting BVH clips (CMU skeletons, Mixamo-style ones brought to CMU's conventions) onto the ``cmu_mb`` rig.

Route (verified in DESIGN.md): world joint rotations from the BVH, changed from BVH axes (Y up, +Z forward) to the
body's (Z up, facing -Y) by ``A``, composed with a per-bone rest correction and the body's T-pose orientation:

    D_b(t) = A G_b(t) A^T  C_b  D_T,b

``C_b`` is the minimal rotation taking the body's T-pose bone axis onto the BVH zero-pose bone direction (found
along the first-child chain, since several CMU joints have zero length). Hips, the hip joints and the clavicles
are not corrected (their BVH directions are proportion artefacts). The root follows the BVH's mid-hip point,
scaled by the leg-length ratio of body and subject.

Other skeletons are first brought to the CMU conventions by :func:`to_cmu_conventions`: joint names without a
namespace (``mixamorig:Hips`` -> ``Hips``) and with the aliases of Mixamo-style rigs (``LeftToe``, a three-joint
spine ``Spine``/``Spine1``/``Spine2``), and the file's axes turned to CMU's (Y up, the character's left +X, facing +Z)
as read from its zero pose. The zero pose (all rotations identity) must be a standing T- or A-pose, as in CMU,
Mixamo and most exporters; rigs whose zero pose is not standing (LAFAN1's bones all lie along one axis) are refused
with a message, since their bone twist cannot be read from it.
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

NAME_ALIASES = {"LeftHandIndex1": "LeftHandFinger1", "RightHandIndex1": "RightHandFinger1",
                "LeftToe": "LeftToeBase", "RightToe": "RightToeBase"}
"""BVH joint name (without namespace) -> body bone name where the two differ (CMU, Mixamo and similar rigs)."""

THREE_JOINT_SPINE = {"Spine": "LowerBack", "Spine1": "Spine", "Spine2": "Spine1"}
"""Mixamo-style spines (Hips-Spine-Spine1-Spine2-Neck, no LowerBack) onto CMU's LowerBack-Spine-Spine1."""

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


def body_joint_names(names: list[str]) -> list[str]:
    """The body-rig name of each BVH joint: namespace dropped (``mixamorig:LeftArm``, ``rig|LeftArm``), aliases
    of :data:`NAME_ALIASES` applied, and a three-joint spine without ``LowerBack`` mapped by
    :data:`THREE_JOINT_SPINE`. Names the rig does not know are kept as they are (and ignored)."""
    bare = [n.rsplit(":", 1)[-1].rsplit("|", 1)[-1] for n in names]
    bare = [NAME_ALIASES.get(n, n) for n in bare]
    if "Spine2" in bare and "LowerBack" not in bare:
        bare = [THREE_JOINT_SPINE.get(n, n) for n in bare]
    return bare


def _signed_axis(v: np.ndarray) -> np.ndarray:
    """The coordinate axis (with sign) nearest to ``v``: a (3,) vector of one +-1 and two zeros."""
    axis = np.zeros(3)
    k = int(np.argmax(np.abs(v)))
    axis[k] = np.sign(v[k]) if v[k] != 0 else 1.0
    return axis


def file_axes_to_cmu(clip: BvhClip, index: dict[str, int]) -> np.ndarray:
    """(3, 3) rotation (a signed permutation) from the file's axes to CMU's: Y up, the character's left +X,
    facing +Z (= left x up). Up is the zero pose's hips-to-head direction, left its right-to-left hip (and
    shoulder) direction, each snapped to the nearest coordinate axis, so a CMU file gets the identity exactly.

    Raises:
        MotionError: when the zero pose gives no up and left axes at right angles, or its legs do not point down
            from the hips (not a standing skeleton).
    """
    pos = np.zeros_like(clip.offsets)
    for j, p in enumerate(clip.parents):  # zero pose, a few dozen joints
        pos[j] = clip.offsets[j] if p < 0 else pos[p] + clip.offsets[j]
    up = _signed_axis(pos[index["Head"]] - pos[index["Hips"]])
    left = pos[index["LeftUpLeg"]] - pos[index["RightUpLeg"]] + pos[index["LeftArm"]] - pos[index["RightArm"]]
    left = _signed_axis(left)
    if abs(float(up @ left)) > 0.5:
        raise MotionError(f"{clip.name}: cannot tell the skeleton's up and left axes from its zero pose "
                          "(the head is not above the hips, or the left joints are not beside the right ones)")
    for side in ("Left", "Right"):
        leg = pos[index[f"{side}Foot"]] - pos[index[f"{side}UpLeg"]]
        if float(leg @ up) > -0.5 * float(np.linalg.norm(leg)):
            raise MotionError(f"{clip.name}: the skeleton's zero pose is not standing (the {side.lower()} leg does "
                              "not point down from the hips); export the clip with a T-pose or A-pose rest")
    return np.stack([left, up, np.cross(left, up)])


def to_cmu_conventions(clip: BvhClip, rig_names: list[str]) -> BvhClip:
    """``clip`` with body-rig joint names (:func:`body_joint_names`) and turned to CMU's axes
    (:func:`file_axes_to_cmu`): offsets and root R x, local rotations R L R^T. A CMU clip comes back unchanged.
    ``rig_names``: the body's bone names, to name the unknown joints when the clip does not fit.

    Raises:
        MotionError: when joints the rig needs are missing, or the axes cannot be read.
    """
    names = body_joint_names(clip.joint_names)
    index = {n: i for i, n in enumerate(names)}
    missing = [n for n in REQUIRED_JOINTS if n not in index]
    if missing:
        unknown = [n for n, o in zip(names, clip.joint_names, strict=True)
                   if n not in rig_names and not o.endswith("_End")]
        raise MotionError(
            f"{clip.name}: skeleton does not match the body rig (CMU or Mixamo joint names): missing joints "
            f"{', '.join(missing)}" + (f"; unknown joints {', '.join(unknown[:6])}" if unknown else "")
        )
    turn = file_axes_to_cmu(clip, index)
    if np.array_equal(turn, np.eye(3)):
        rotations, root, offsets, ends = clip.local_rotations, clip.root_positions, clip.offsets, clip.end_offsets
    else:
        rotations = np.einsum("ik,fjkl,ml->fjim", turn, clip.local_rotations, turn)
        root, offsets, ends = clip.root_positions @ turn.T, clip.offsets @ turn.T, clip.end_offsets @ turn.T
    return BvhClip(clip.name, names, clip.parents, offsets, ends, rotations, root, clip.fps)


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
    """Retarget a parsed clip (CMU or Mixamo-style skeleton, any axes, :func:`to_cmu_conventions`) onto
    ``body`` and resample it to ``fps``.

    Raises:
        MotionError: when the clip lacks joints the body rig needs, or its axes cannot be read.
    """
    clip = to_cmu_conventions(clip, body.bone_names)
    bvh_index = {n: i for i, n in enumerate(clip.joint_names)}

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
