"""Motion: BVH clips, retargeting onto the body rig, 30 fps resampling, posing and the shipped clip library."""

from smln.motion.bvh import BvhClip, MotionError, load_bvh
from smln.motion.library import clip_split, list_clips, load_body_sequence, load_motion, manifest
from smln.motion.posing import BodySequence, pose_sequence
from smln.motion.retarget import Motion, retarget

__all__ = [
    "BodySequence", "BvhClip", "Motion", "MotionError", "clip_split", "list_clips", "load_body_sequence",
    "load_bvh", "load_motion", "manifest", "pose_sequence", "retarget",
]
