"""smln.garments"""
