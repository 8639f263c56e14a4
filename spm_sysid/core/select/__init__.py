"""Choosing among structures on held-out data.

Validated selection, and the simulation focus's one scorer.
"""
