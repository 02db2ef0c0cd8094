"""Posing a body along a retargeted motion, with the feet kept on the floor z = 0."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from smln.body.model import Body
from smln.body.skinning import compose, lbs, world_orient_fk
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

    def to(self, device: torch.device | str) -> BodySequence:
        """The sequence with its tensors on ``device`` (itself when they already are)."""
        dev = torch.device(device)
        if self.vertices.device == dev:
            return self
        return BodySequence(self.vertices.to(dev), self.faces.to(dev), self.transforms.to(dev), self.fps, self.name,
                            self.shape)


def body_speed(vertices: torch.Tensor | np.ndarray) -> np.ndarray:
    """(T,) float64 mean vertex displacement from frame t-1 to t of a (T, Vb, 3) body sequence, m/frame (0 at t = 0).

    How fast the body moves at each frame: the training sampler's ``start_sampling="speed"`` weights
    (:class:`smln.train.EpisodeSampler`) and ``bench/hcoll_speed.py``."""
    b = torch.as_tensor(vertices)  # its own float precision (float32 bodies: no float64 copy of a whole clip)
    speed = np.zeros(b.shape[0])
    speed[1:] = (b[1:] - b[:-1]).norm(dim=-1).mean(dim=-1).double().cpu().numpy()
    return speed


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


def preroll_sequence(body: Body, sequence: BodySequence, frame: int = 0, num_frames: int = 20,
                     match_velocity: bool = True) -> BodySequence:
    """A lead-in from the T-pose to ``sequence``'s pose at ``frame``, for simulators that start from the rest pose.

    Each bone's world orientation is slerped from its T-pose orientation to its orientation at ``frame`` with a
    smoothstep easing; the skeleton is rebuilt with :func:`~smln.body.skinning.world_orient_fk`, so bone lengths
    hold at every step (unlike blending vertices or transforms). The root's head starts at rest and follows a
    cubic Hermite path that arrives at ``frame`` with the clip's root velocity there (frame -> frame + 1), so a
    running clip does not start by slamming the body into cloth that stands still (``match_velocity=False``:
    smoothstep, arriving at rest). Garments at rest in the T-pose can then be simulated into the clip's pose
    without starting from the interpenetrations of skinning (``bench/physics_reference.py --preroll``).

    Args:
        body: the body the sequence was posed on.
        sequence: the posed clip.
        frame: the pose to end on.
        num_frames: length of the lead-in; its last frame equals ``sequence`` at ``frame``.
        match_velocity: arrive with the clip's root velocity (needs frame + 1 in the clip; else at rest).

    Returns:
        :class:`BodySequence` of ``num_frames`` frames (vertices (N, Vb, 3), T-pose -> posed transforms (N, B, 3, 4)).
    """
    from scipy.spatial.transform import Rotation, Slerp

    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    rest_rot = body.rest_bone_poses[:, :3, :3].double()
    heads = body.rest_bone_poses[:, :3, 3].double()
    a_start = body.tpose_transforms.double()  # A-pose -> T-pose
    a_end = compose(sequence.transforms[frame].double(), a_start)  # A-pose -> posed
    d_start = (a_start[:, :, :3] @ rest_rot).numpy()
    d_end = (a_end[:, :, :3] @ rest_rot).numpy()
    root_start = (a_start[0, :, :3] @ heads[0] + a_start[0, :, 3]).numpy()
    root_end = (a_end[0, :, :3] @ heads[0] + a_end[0, :, 3]).numpy()
    u = np.arange(1, num_frames + 1) / num_frames
    s = u * u * (3.0 - 2.0 * u)
    orient = np.empty((num_frames, body.num_bones, 3, 3))
    for b in range(body.num_bones):  # loop over ~40 bones, vectorised over the lead-in frames
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([d_start[b], d_end[b]])))
        orient[:, b] = slerp(s).as_matrix()
    root = root_start[None] + s[:, None] * (root_end - root_start)[None]
    if match_velocity and frame + 1 < sequence.num_frames:
        a_next = compose(sequence.transforms[frame + 1].double(), a_start)
        velocity = (a_next[0, :, :3] @ heads[0] + a_next[0, :, 3]).numpy() - root_end  # m per frame
        root += ((u ** 3 - u ** 2) * num_frames)[:, None] * velocity[None]  # Hermite h11 * end tangent
    anny_tf = world_orient_fk(body.rest_bone_poses.double(), body.bone_parents, torch.from_numpy(orient),
                              torch.from_numpy(root)).float()
    vertices = lbs(body.anny_rest_vertices, body.skin_indices, body.skin_weights, anny_tf)
    return BodySequence(vertices=vertices, faces=sequence.faces, transforms=body.garment_transforms(anny_tf),
                        fps=sequence.fps, name=f"{sequence.name}:preroll", shape=sequence.shape)
