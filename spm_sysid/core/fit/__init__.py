"""Fitting structures.

The regression problem (built once), least squares, the batched evaluator, criteria,
refinement on the free-run error.
"""
