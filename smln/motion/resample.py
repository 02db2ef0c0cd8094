"""Resampling motion to the simulation rate: quaternion slerp for rotations, linear for positions."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def sample_times(num_frames: int, src_fps: float, dst_fps: float) -> np.ndarray:
    """Fractional source-frame indices of the output frames, covering the same duration.

    A clip of ``num_frames`` samples at ``src_fps`` lasts ``(num_frames - 1) / src_fps`` s; the output holds
    ``floor(duration * dst_fps) + 1`` frames.
    """
    duration = (num_frames - 1) / src_fps
    count = int(np.floor(duration * dst_fps + 1e-9)) + 1
    return np.arange(count) * (src_fps / dst_fps)


def slerp_rotations(rotations: np.ndarray, positions: np.ndarray, src_fps: float, dst_fps: float):
    """Resample per-joint rotations and root positions.

    Args:
        rotations: (F, J, 3, 3) rotation matrices.
        positions: (F, 3) root positions.
        src_fps, dst_fps: rates in frames per second.

    Returns:
        ((T, J, 3, 3) rotations, (T, 3) positions).
    """
    num_frames, num_joints = rotations.shape[:2]
    t = sample_times(num_frames, src_fps, dst_fps)
    i0 = np.clip(np.floor(t).astype(np.int64), 0, num_frames - 1)
    i1 = np.clip(i0 + 1, 0, num_frames - 1)
    alpha = (t - i0)[:, None]

    quat = Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_quat().reshape(num_frames, num_joints, 4)
    q0, q1 = quat[i0], quat[i1]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)  # shortest arc
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    small = sin < 1e-6
    a = np.broadcast_to(alpha[:, None, :], theta.shape)
    w0 = np.where(small, 1.0 - a, np.sin((1.0 - a) * theta) / np.where(small, 1.0, sin))
    w1 = np.where(small, a, np.sin(a * theta) / np.where(small, 1.0, sin))
    q = w0 * q0 + w1 * q1
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    out_rot = Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(len(t), num_joints, 3, 3)
    out_pos = (1.0 - alpha) * positions[i0] + alpha * positions[i1]
    return out_rot, out_pos
