"""smln.body"""
