"""smln.geometry"""
