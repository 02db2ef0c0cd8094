"""Motion: every shipped clip loads and retargets; feet on the floor; joints follow the BVH; bad files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from smln.motion import MotionError, list_clips, load_bvh, load_motion, manifest, pose_sequence, retarget
from smln.motion.bvh import CMU_UNIT, detect_unit, zero_pose_extent
from smln.motion.library import clip_path
from smln.motion.resample import sample_times, slerp_rotations
from smln.motion.retarget import BVH_TO_BODY, posed_bone_ends


def test_split_is_disjoint_and_about_seventy_thirty():
    train, test = set(list_clips("train")), set(list_clips("test"))
    assert not train & test and len(train) + len(test) == len(manifest())
    assert 0.6 < len(train) / len(manifest()) < 0.8
    kinds_test = {c["kind"] for c in manifest() if c["split"] == "test"}
    kinds_train = {c["kind"] for c in manifest() if c["split"] == "train"}
    assert kinds_test <= kinds_train  # every tested kind was also trained on


@pytest.mark.slow
@pytest.mark.parametrize("name", list_clips())
def test_every_clip_retargets_without_nan(name, body):
    motion = load_motion(name, body)
    assert motion.num_frames > 10 and motion.fps == 30
    assert torch.isfinite(motion.world_orientations).all() and torch.isfinite(motion.root_positions).all()
    seq = pose_sequence(body, motion)
    assert torch.isfinite(seq.vertices).all()
    # no start-up glitch (CMU reference pose, frozen or jumping frames): the first step is like the next ones
    steps = (seq.vertices[1:8] - seq.vertices[:7]).norm(dim=-1).mean(dim=-1)
    assert steps[0] <= 2 * steps[1:].median() + 0.01, steps
    # the duration survives 120 -> 30 fps resampling
    clip = load_bvh(clip_path(name))
    assert abs((seq.num_frames - 1) / 30 - clip.duration) < 1 / 30 + 1e-6


def test_posed_body_stays_watertight(walk_sequence):
    for f in (0, walk_sequence.num_frames // 2, walk_sequence.num_frames - 1):
        mesh = trimesh.Trimesh(walk_sequence.vertices[f].numpy(), walk_sequence.faces.numpy(), process=False)
        assert mesh.is_watertight and mesh.volume > 0.02


def test_walk_keeps_feet_on_the_floor(walk_sequence):
    """The floor is z = 0: the lowest body vertex is within 3 cm of it on at least 90 % of the frames."""
    lowest = walk_sequence.vertices[..., 2].amin(dim=1)
    assert (lowest.abs() < 0.03).float().mean() > 0.9
    assert lowest.min() > -0.03


def test_retargeted_joints_follow_the_bvh(body):
    """Bone directions match the BVH's own forward kinematics; leg joints match its scaled positions."""
    clip = load_bvh(clip_path("02_01_walk"))
    motion = retarget(clip, body)
    heads, tails = posed_bone_ends(body, motion)
    rot, root = slerp_rotations(clip.local_rotations, clip.root_positions, clip.fps, 30)
    clip30 = type(clip)(clip.name, clip.joint_names, clip.parents, clip.offsets, clip.end_offsets, rot, root, 30)
    joints = clip30.joint_positions() @ BVH_TO_BODY.T
    idx = {n: i for i, n in enumerate(clip.joint_names)}
    for bone, child in (("LeftUpLeg", "LeftLeg"), ("LeftLeg", "LeftFoot"), ("RightLeg", "RightFoot"),
                        ("LeftForeArm", "LeftHand"), ("RightArm", "RightForeArm")):
        b = body.bone_index(bone)
        d_body = torch.nn.functional.normalize(tails[:, b] - heads[:, b], dim=-1).numpy()
        d_bvh = joints[:, idx[child]] - joints[:, idx[bone]]
        d_bvh /= np.linalg.norm(d_bvh, axis=-1, keepdims=True)
        angle = np.degrees(np.arccos(np.clip((d_body * d_bvh).sum(-1), -1, 1)))
        assert angle.max() < 1.0, (bone, angle.max())
    # knees and ankles relative to the mid-hip point, after scaling the subject to the body's leg length
    mid_b = 0.5 * (heads[:, body.bone_index("LeftUpLeg")] + heads[:, body.bone_index("RightUpLeg")]).numpy()
    mid_j = 0.5 * (joints[:, idx["LeftUpLeg"]] + joints[:, idx["RightUpLeg"]])
    for name in ("LeftLeg", "LeftFoot", "RightLeg", "RightFoot"):
        err = np.linalg.norm((heads[:, body.bone_index(name)].numpy() - mid_b)
                             - motion.leg_scale * (joints[:, idx[name]] - mid_j), axis=-1)
        assert err.mean() < 0.05, (name, err.mean())


def test_resampling_keeps_duration_and_interpolates_rotations():
    t = sample_times(121, 120, 30)
    assert len(t) == 31 and t[-1] == 120
    angles = np.linspace(0, np.pi / 2, 5)  # 5 frames at 4 fps: a quarter turn about Z
    rots = np.stack([[[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]] for a in angles])[:, None]
    out, _ = slerp_rotations(rots, np.zeros((5, 3)), 4, 8)
    mid = np.arctan2(out[1, 0, 1, 0], out[1, 0, 0, 0])
    assert abs(mid - np.pi / 16) < 1e-9  # halfway between 0 and pi/8, not an Euler lerp artefact


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "empty"),
        (b"\x00\x01junk\xff" * 100, "not a BVH"),
        (b"hello world\n", "not a BVH"),
    ],
)
def test_bad_files_get_a_clear_error(tmp_path, content, message):
    path = tmp_path / "bad.bvh"
    path.write_bytes(content)
    with pytest.raises(MotionError, match=message):
        load_bvh(path)


def test_truncated_bvh_is_refused(tmp_path):
    text = clip_path("02_01_walk").read_text()
    path = tmp_path / "trunc.bvh"
    path.write_text(text[: len(text) // 2])
    with pytest.raises(MotionError, match="bad.bvh|trunc"):
        load_bvh(path)


def test_unknown_skeleton_is_refused(tmp_path, body):
    text = clip_path("02_01_walk").read_text()
    for old in ("LeftUpLeg", "RightUpLeg"):
        text = text.replace(f"JOINT {old}\n", f"JOINT Thigh{old[0]}\n")
    path = tmp_path / "other_rig.bvh"
    path.write_text(text)
    with pytest.raises(MotionError, match="missing joints"):
        retarget(load_bvh(path), body)


def _write_bvh(path, clip, names, turn, unit):
    """Write ``clip`` as a BVH file of another source: joints renamed by ``names``, axes turned by ``turn`` (file =
    turn @ CMU), lengths in ``unit`` m per file unit, rotations as ZXY Euler channels (an independent writer)."""
    from scipy.spatial.transform import Rotation

    offsets, ends = clip.offsets @ turn.T / unit, clip.end_offsets @ turn.T / unit
    local = np.einsum("ik,fjkl,ml->fjim", turn, clip.local_rotations, turn)
    root = clip.root_positions @ turn.T / unit
    children = {j: [c for c, p in enumerate(clip.parents) if p == j] for j in range(len(names))}
    lines = ["HIERARCHY"]

    def joint(j, depth):
        pad = "  " * depth
        kind = "ROOT" if clip.parents[j] < 0 else "JOINT"
        channels = "6 Xposition Yposition Zposition" if kind == "ROOT" else "3"
        lines.extend([f"{pad}{kind} {names[j]}", pad + "{", f"{pad}  OFFSET {' '.join(f'{v:.6f}' for v in offsets[j])}",
                      f"{pad}  CHANNELS {channels} Zrotation Xrotation Yrotation"])
        for c in children[j]:
            joint(c, depth + 1)
        if not children[j]:
            lines.extend([f"{pad}  End Site", pad + "  {", f"{pad}    OFFSET {' '.join(f'{v:.6f}' for v in ends[j])}",
                          pad + "  }"])
        lines.append(pad + "}")

    joint(0, 0)
    euler = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_euler("ZXY", degrees=True).reshape(len(root), -1)
    lines += ["MOTION", f"Frames: {len(root)}", f"Frame Time: {1 / clip.fps:.8f}"]
    lines += [" ".join(f"{v:.6f}" for v in np.concatenate([r, e])) for r, e in zip(root, euler, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def test_a_mixamo_style_z_up_centimetre_file_retargets_as_the_cmu_clip(tmp_path, body):
    """The same motion written as another source would (``mixamorig:`` names, a Spine/Spine1/Spine2 spine without
    LowerBack, LeftToe, Z up facing +X, centimetres) reads as the CMU original: same unit, same frames, and the
    retargeted body orientations and root path agree with the original's."""
    clip = load_bvh(clip_path("02_01_walk"))
    rename = {"LowerBack": "Spine", "Spine": "Spine1", "Spine1": "Spine2", "LeftToeBase": "LeftToe",
              "RightToeBase": "RightToe"}
    names = ["mixamorig:" + rename.get(n, n) for n in clip.joint_names]
    turn = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # CMU left X -> Y, up Y -> Z, facing Z -> X
    path = tmp_path / "mixamo_walk.bvh"
    _write_bvh(path, clip, names, turn, unit=0.01)
    other = load_bvh(path)
    assert other.num_frames == clip.num_frames
    np.testing.assert_allclose(other.offsets, clip.offsets @ turn.T, atol=1e-7)  # read in metres again
    reference, converted = retarget(clip, body), retarget(other, body)
    assert converted.num_frames == reference.num_frames
    np.testing.assert_allclose(converted.world_orientations, reference.world_orientations, atol=1e-4)
    np.testing.assert_allclose(converted.root_positions, reference.root_positions, atol=1e-4)


@pytest.mark.parametrize("unit, expected", [(CMU_UNIT, CMU_UNIT), (0.01, 0.01), (1.0, 1.0), (0.0254, 0.0254),
                                            (0.001, 0.001)])
def test_the_unit_is_read_from_the_skeleton_size(unit, expected):
    """A 1.5 m tall zero pose written in each unit is read back in that unit (the CMU unit wins where plausible)."""
    assert detect_unit(1.5 / unit) == expected
    parents, offsets = [-1, 0, 1], np.array([[0, 0, 0], [0, -0.9, 0], [0, 1.5, 0]]) / unit
    assert zero_pose_extent(offsets, parents) == pytest.approx(1.5 / unit)


@pytest.mark.parametrize("bones, direction, message", [
    (("Spine", "Spine1", "Neck1", "Head"), (1.0, 0.0, 0.0), "up and left axes"),  # the spine points to the left
    (("LeftLeg", "LeftFoot"), (0.0, 1.0, 0.0), "left leg does not point down"),  # a LAFAN1-like rest, legs up
])
def test_a_skeleton_whose_zero_pose_is_not_standing_is_refused(tmp_path, body, bones, direction, message):
    """A zero pose with the head beside the hips gives no up axis, one with the legs pointing up no readable bone
    twist: both are refused with a clear error instead of retargeted into a wrong motion."""
    clip = load_bvh(clip_path("02_01_walk"))
    offsets = clip.offsets.copy()
    for name in bones:
        j = clip.joint_names.index(name)
        offsets[j] = np.linalg.norm(offsets[j]) * np.asarray(direction)
    bent = type(clip)(clip.name, clip.joint_names, clip.parents, offsets, clip.end_offsets, clip.local_rotations,
                      clip.root_positions, clip.fps)
    path = tmp_path / "bent.bvh"
    _write_bvh(path, bent, clip.joint_names, np.eye(3), unit=CMU_UNIT)
    with pytest.raises(MotionError, match=message):
        retarget(load_bvh(path), body)


def test_absurd_frame_count_is_refused(tmp_path):
    text = clip_path("02_01_walk").read_text()
    head, _, _ = text.partition("Frames:")
    path = tmp_path / "huge.bvh"
    path.write_text(head + "Frames: 999999999\nFrame Time: 0.008333\n0 0 0\n")
    with pytest.raises(MotionError, match="over the limit"):
        load_bvh(path)


def test_preroll_goes_from_the_t_pose_to_the_clip_frame_with_rigid_bones(body, walk_sequence):
    """The lead-in ends exactly on the clip's pose, starts near the T-pose, eases in, arrives with the clip's
    velocity (or at rest), and keeps every bone's length (parent head -> child head) at every frame."""
    from smln.body.skinning import compose
    from smln.motion.posing import preroll_sequence

    lead = preroll_sequence(body, walk_sequence, frame=1, num_frames=24)
    assert lead.vertices.shape == (24, *walk_sequence.vertices.shape[1:])
    assert torch.allclose(lead.vertices[-1], walk_sequence.vertices[1], atol=1e-5)
    assert torch.allclose(lead.transforms[-1], walk_sequence.transforms[1], atol=1e-5)
    # first step: smoothstep(1/24) ~ 0.5 % of the way
    assert (lead.vertices[0] - body.rest_vertices).norm(dim=-1).max() < 0.01
    steps = (lead.vertices[1:] - lead.vertices[:-1]).norm(dim=-1).max(dim=1).values
    assert steps[0] < steps[len(steps) // 2]
    # arrival: the mean body velocity of the last step is the clip's (frame 1 -> 2) one, to a few mm per frame
    clip_v = (walk_sequence.vertices[2] - walk_sequence.vertices[1]).mean(0)
    assert clip_v.norm() > 0.005
    assert ((lead.vertices[-1] - lead.vertices[-2]).mean(0) - clip_v).norm() < 0.3 * clip_v.norm()
    rest_end = preroll_sequence(body, walk_sequence, frame=1, num_frames=24, match_velocity=False)
    assert torch.allclose(rest_end.vertices[-1], walk_sequence.vertices[1], atol=1e-5)
    assert (rest_end.vertices[-1] - rest_end.vertices[-2]).norm(dim=-1).max() < 0.25 * steps.max()
    # posed bone heads: h_c = A_c(head_c) with A the A-pose -> posed transform
    anny = compose(lead.transforms.double(), body.tpose_transforms.double().unsqueeze(0))
    heads = body.rest_bone_poses[:, :3, 3].double()
    posed = (anny[..., :3] @ heads[None, :, :, None]).squeeze(-1) + anny[..., 3]
    parents = torch.tensor(body.bone_parents)
    child = torch.nonzero(parents >= 0).squeeze(1)
    lengths = (posed[:, child] - posed[:, parents[child]]).norm(dim=-1)  # (N, C)
    assert torch.allclose(lengths, lengths[:1].expand_as(lengths), atol=1e-5)
    with pytest.raises(ValueError):
        preroll_sequence(body, walk_sequence, num_frames=0)


def test_a_shipped_clip_is_unpacked_once_byte_for_byte_into_the_cache(tmp_path, monkeypatch):
    import gzip
    import os

    from smln.motion.library import MOTION_DIR

    monkeypatch.setenv("SMLN_CACHE_DIR", str(tmp_path / "cache"))
    gz = MOTION_DIR / "02_01_walk.bvh.gz"
    path = clip_path("02_01_walk")
    assert path.name == "02_01_walk.bvh" and (tmp_path / "cache" / "motions") in path.parents
    assert path.read_bytes() == gzip.open(gz).read()
    assert path.read_text().startswith("HIERARCHY")
    os.utime(path, (1, 1))  # a second use reads the unpacked file, it does not write it again
    assert clip_path("02_01_walk") == path and path.stat().st_mtime == 1


def test_a_damaged_packed_clip_or_an_unwritable_cache_is_handled(tmp_path, monkeypatch):
    from smln.motion.library import MOTION_DIR, unpacked_clip

    bad = tmp_path / "bad.bvh.gz"
    bad.write_bytes(b"not gzip at all")
    monkeypatch.setenv("SMLN_CACHE_DIR", str(tmp_path / "cache"))
    with pytest.raises(MotionError, match="bad.bvh.gz: cannot unpack"):
        unpacked_clip(bad)
    with pytest.raises(MotionError, match="no such file"):
        unpacked_clip(tmp_path / "missing.bvh.gz")
    packed = (MOTION_DIR / "02_01_walk.bvh.gz").read_bytes()
    broken = tmp_path / "broken.bvh.gz"  # a gzip header, then damaged deflate data
    broken.write_bytes(packed[:20] + bytes(b ^ 0x5A for b in packed[20:400]) + packed[400:])
    with pytest.raises(MotionError, match="broken.bvh.gz: cannot unpack"):
        unpacked_clip(broken)
    blocker = tmp_path / "file_not_dir"
    blocker.write_text("x")  # the cache root is a file: nothing can be made under it
    monkeypatch.setenv("SMLN_CACHE_DIR", str(blocker))
    path = unpacked_clip(MOTION_DIR / "02_03_run_jog.bvh.gz")
    assert path.is_file() and blocker not in path.parents and path.read_text().startswith("HIERARCHY")
