"""Forward kinematics in anny's world-orientation parameterisation, and linear blend skinning.

Both are written for whole sequences at once: frames are a batch dimension and the bone chain is walked
once per bone (31 bones), never per vertex.
"""

from __future__ import annotations

import torch


def world_orient_fk(
    rest_bone_poses: torch.Tensor,
    bone_parents: list[int],
    world_orientations: torch.Tensor,
    root_positions: torch.Tensor,
) -> torch.Tensor:
    """Skinning transforms for world bone orientations (anny's ``"world-orient"`` rule).

    Each bone ``c`` with rest pose ``P_c = [R_c | h_c]`` takes the world orientation ``D_c``; its head follows its
    parent. With ``G_c = D_c R_c^T`` the skinning transform is ``T_c = [G_c | T_p(h_c) - G_c h_c]``; the root's head
    is placed at ``root_positions``.

    Args:
        rest_bone_poses: (B, 4, 4) float32 rest bone poses (rotation = bone frame, translation = head, meters).
        bone_parents: length-B parent indices, -1 for the root; parents come before children.
        world_orientations: (T, B, 3, 3) float32 world bone orientations.
        root_positions: (T, 3) float32 world position of the root bone's head, meters.

    Returns:
        (T, B, 3, 4) float32 rest -> posed transforms ``[G | t]``.
    """
    rot_rest = rest_bone_poses[:, :3, :3]
    heads = rest_bone_poses[:, :3, 3]
    g = world_orientations @ rot_rest.transpose(-1, -2)  # (T, B, 3, 3)
    num_frames, num_bones = g.shape[:2]
    trans = torch.empty(num_frames, num_bones, 3, dtype=g.dtype, device=g.device)
    for c, p in enumerate(bone_parents):
        if p < 0:
            trans[:, c] = root_positions - g[:, c] @ heads[c]
        else:
            head_posed = g[:, p] @ heads[c] + trans[:, p]
            trans[:, c] = head_posed - g[:, c] @ heads[c]
    return torch.cat([g, trans.unsqueeze(-1)], dim=-1)


def compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Compose rigid/affine transforms ``a ∘ b`` given as (..., 3, 4) blocks."""
    rot = a[..., :3] @ b[..., :3]
    trans = a[..., :3] @ b[..., 3:] + a[..., 3:]
    return torch.cat([rot, trans], dim=-1)


def invert_rigid(t: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms (..., 3, 4) (rotation part orthonormal)."""
    rot_t = t[..., :3].transpose(-1, -2)
    return torch.cat([rot_t, -rot_t @ t[..., 3:]], dim=-1)


def lbs(
    points: torch.Tensor,
    skin_indices: torch.Tensor,
    skin_weights: torch.Tensor,
    transforms: torch.Tensor,
    chunk: int = 64,
) -> torch.Tensor:
    """Linear blend skinning of rest points by per-frame bone transforms.

    Args:
        points: (N, 3) float32 rest positions, meters.
        skin_indices: (N, K) int64 bone indices.
        skin_weights: (N, K) float32 weights (rows sum to 1).
        transforms: (T, B, 3, 4) or (T, B, 4, 4) float32 rest -> posed bone transforms.
        chunk: frames blended at once (bounds memory to about chunk * N * 12 floats).

    Returns:
        (T, N, 3) float32 posed positions.
    """
    transforms = transforms[..., :3, :4]
    num_frames, num_bones = transforms.shape[:2]
    n = points.shape[0]
    dense = torch.zeros(n, num_bones, dtype=points.dtype, device=points.device)
    dense.scatter_add_(1, skin_indices, skin_weights.to(points.dtype))
    homo = torch.cat([points, torch.ones(n, 1, dtype=points.dtype, device=points.device)], dim=1)  # (N, 4)
    out = torch.empty(num_frames, n, 3, dtype=points.dtype, device=points.device)
    flat = transforms.reshape(num_frames, num_bones, 12).to(points.dtype)
    for start in range(0, num_frames, chunk):
        stop = min(start + chunk, num_frames)
        blended = torch.einsum("nb,tbk->tnk", dense, flat[start:stop]).reshape(stop - start, n, 3, 4)
        out[start:stop] = torch.einsum("tnij,nj->tni", blended, homo)
    return out
