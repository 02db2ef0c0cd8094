"""smln.model: MLPs, normalisers, the hierarchical processor, the repulsion layer and the SMLN network."""

from smln.model.mlp import MLP
from smln.model.normalizer import Normalizer
from smln.model.processor import MessagePassingBlock, Processor
from smln.model.repulsion import RepulsionLayer
from smln.model.smln import SMLN, SMLNConfig

__all__ = ["MLP", "SMLN", "MessagePassingBlock", "Normalizer", "Processor", "RepulsionLayer", "SMLNConfig"]
