"""SMLN: self-supervised multi-layer garment animation with a graph network and a repulsion layer."""

__version__ = "0.1.0"
