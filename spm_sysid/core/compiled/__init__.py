"""Compiled kernels.

The registry (numba's JIT or the ahead-of-time build), the builder, the numeric kernels.
"""
