"""smln.graph"""
