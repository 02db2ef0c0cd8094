"""smln.losses"""
