"""Judging a model and its data.

Validation, correlation tests, excitation and conditioning, lag and degree proposals.
"""
