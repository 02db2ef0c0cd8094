"""smln.model"""
