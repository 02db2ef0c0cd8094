"""Self-supervised physics losses (paper Eq. 17-25), one term per module, all differentiable torch energies.

Build :class:`ClothRest` once per cloth and :class:`BodyStep` once per step, then call :func:`total_loss`.
Every term is a sum over vertices/faces/edges (not a mean), in J, except the cubic penalties (m^3) whose
weights in :class:`LossWeights` carry the units.
"""

from smln.losses.bending import bending_energy
from smln.losses.collision import COLLISION_EPS, collision_energy
from smln.losses.friction import FRICTION_RADIUS, LAYER_FRICTION_RADIUS, friction_energy, layer_friction_energy
from smln.losses.gravity import gravity_energy
from smln.losses.inertia import inertia_energy
from smln.losses.repulsion import PAIR_RADIUS, REPULSION_EPS, layer_pairs, repulsion_energy
from smln.losses.rest import ClothRest
from smln.losses.stretch import stretch_energy
from smln.losses.total import BodyStep, LossWeights, pre_layer_contact_loss, total_loss

__all__ = [
    "COLLISION_EPS",
    "FRICTION_RADIUS",
    "PAIR_RADIUS",
    "REPULSION_EPS",
    "BodyStep",
    "ClothRest",
    "LossWeights",
    "bending_energy",
    "collision_energy",
    "friction_energy",
    "layer_friction_energy",
    "LAYER_FRICTION_RADIUS",
    "gravity_energy",
    "inertia_energy",
    "layer_pairs",
    "repulsion_energy",
    "pre_layer_contact_loss",
    "stretch_energy",
    "total_loss",
]
