"""smln.motion"""
