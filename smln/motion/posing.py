"""Posing a body along a retargeted motion, with the feet kept on the floor z = 0."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smln.body.model import Body
from smln.body.skinning import lbs, world_orient_fk
from smln.motion.retarget import Motion


@dataclass
class BodySequence:
    """A posed body over a clip.

    Attributes:
        vertices: (T, Vb, 3) float32 body vertices, meters.
        faces: (Fb, 3) int64 body faces.
        transforms: (T, B, 3, 4) float32 T-pose -> posed bone transforms (skin garments with these).
        fps: frames per second.
        name: clip name; shape: body shape preset.
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    transforms: torch.Tensor
    fps: float
    name: str = ""
    shape: str = ""

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])

    def slice(self, start: int, stop: int) -> BodySequence:
        """Frames ``start:stop`` as a new sequence (views, no copies)."""
        return BodySequence(self.vertices[start:stop], self.faces, self.transforms[start:stop], self.fps,
                            self.name, self.shape)


def floor_offsets(lowest: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Per-frame vertical offsets that put the feet on z = 0.

    CMU floors drift (feet rise several cm over a long walk), so a linear trend of the lower envelope of the
    lowest-vertex height is removed first; then the whole clip is shifted so that the 5th percentile of the lowest
    vertex sits on z = 0. Flight phases (runs, jumps) stay in the air: frames are not pinned individually.

    Args:
        lowest: (T,) height of the lowest body vertex per frame, meters.

    Returns:
        (T,) offsets to add to z.
    """
    t = np.arange(len(lowest), dtype=np.float64)
    keep = np.ones(len(lowest), dtype=bool)
    coef = np.array([0.0, float(np.median(lowest))])
    for _ in range(iterations):
        if keep.sum() < 2:
            break
        coef = np.polyfit(t[keep], lowest[keep], 1)
        resid = lowest - np.polyval(coef, t)
        keep = resid <= np.median(resid[keep])
    trend = np.polyval(coef, t) - coef[1]
    detrended = lowest - trend
    return -(trend + np.percentile(detrended, 5))


def pose_sequence(body: Body, motion: Motion, ground: bool = True) -> BodySequence:
    """Pose ``body`` along ``motion`` (whole sequence at once).

    Args:
        body: the body shape.
        motion: a clip retargeted to this body (:func:`smln.motion.retarget.retarget`).
        ground: remove floor drift and put the feet on z = 0.

    Returns:
        :class:`BodySequence` with vertices (T, Vb, 3) and T-pose -> posed transforms (T, B, 3, 4).
    """
    anny_tf = world_orient_fk(body.rest_bone_poses, body.bone_parents, motion.world_orientations,
                              motion.root_positions)
    vertices = lbs(body.anny_rest_vertices, body.skin_indices, body.skin_weights, anny_tf)
    transforms = body.garment_transforms(anny_tf)
    if ground:
        dz = torch.from_numpy(floor_offsets(vertices[..., 2].amin(dim=1).double().numpy())).float()
        vertices[..., 2] += dz[:, None]
        transforms[:, :, 2, 3] += dz[:, None]
    return BodySequence(vertices=vertices, faces=body.faces, transforms=transforms, fps=motion.fps,
                        name=motion.name, shape=body.shape)
