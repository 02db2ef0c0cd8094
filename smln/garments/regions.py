"""Body landmarks in the canonical T-pose, measured from the rig, that place garment cuts on any body shape.

All heights and offsets are meters in the body frame (Z up, facing -Y, left side +X, feet on z = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smln.body import Body
from smln.body.skinning import world_orient_fk


@dataclass(frozen=True)
class Landmarks:
    """T-pose landmarks of one body, meters.

    Attributes:
        hips_z: height of the Hips joint (pelvis). waist_z: natural waist (between hips and LowerBack top).
        crotch_z: height where the thighs meet. knee_z, ankle_z: joint heights.
        shoulder_x, elbow_x, wrist_x: |x| of the shoulder, elbow and wrist joints along the T-pose arm.
        shoulder_z: height of the T-pose arm axis. armpit_z: a little below the arm's underside.
        neck_z: base of the neck (Neck joint). neck_y: y of the neck axis. centre_xy: (2,) pelvis axis.
        height: body height.
    """

    hips_z: float
    waist_z: float
    crotch_z: float
    knee_z: float
    ankle_z: float
    shoulder_x: float
    elbow_x: float
    wrist_x: float
    shoulder_z: float
    armpit_z: float
    neck_z: float
    neck_y: float
    centre_xy: tuple[float, float]
    height: float


def tpose_joints(body: Body) -> dict[str, np.ndarray]:
    """Bone head positions (3,) of the canonical T-pose, by bone name."""
    tf = world_orient_fk(
        body.rest_bone_poses, body.bone_parents, body.tpose_orientations[None], body.rest_bone_poses[None, 0, :3, 3]
    )[0]
    heads = torch.einsum("bij,bj->bi", tf[:, :, :3], body.bone_heads) + tf[:, :, 3]
    return {n: heads[i].numpy().astype(np.float64) for i, n in enumerate(body.bone_names)}


def landmarks(body: Body) -> Landmarks:
    """Measure :class:`Landmarks` on ``body`` (T-pose)."""
    j = tpose_joints(body)
    v = body.rest_vertices.numpy().astype(np.float64)
    hips = j["Hips"]
    knee = 0.5 * (j["LeftLeg"][2] + j["RightLeg"][2])
    ankle = 0.5 * (j["LeftFoot"][2] + j["RightFoot"][2])
    # crotch: lowest body point near the mid-sagittal plane between the hips and the knees
    mid = v[(np.abs(v[:, 0]) < 0.012) & (v[:, 2] < hips[2]) & (v[:, 2] > knee)]
    crotch = float(mid[:, 2].min()) if len(mid) else float(hips[2] - 0.1)
    arm = v[(np.abs(v[:, 0]) > j["LeftArm"][0] + 0.03) & (np.abs(v[:, 0]) < j["LeftForeArm"][0])
            & (v[:, 2] > j["LeftArm"][2] - 0.25)]
    arm_bottom = float(np.percentile(arm[:, 2], 2)) if len(arm) else float(j["LeftArm"][2] - 0.05)
    return Landmarks(
        hips_z=float(hips[2]),
        waist_z=float(0.5 * (hips[2] + j["Spine"][2])),
        crotch_z=crotch,
        knee_z=float(knee),
        ankle_z=float(ankle),
        shoulder_x=float(j["LeftArm"][0]),
        elbow_x=float(j["LeftForeArm"][0]),
        wrist_x=float(j["LeftHand"][0]),
        shoulder_z=float(j["LeftArm"][2]),
        armpit_z=arm_bottom - 0.04,
        neck_z=float(j["Neck"][2]),
        neck_y=float(j["Neck"][1]),
        centre_xy=(float(hips[0]), float(hips[1])),
        height=float(v[:, 2].max()),
    )
