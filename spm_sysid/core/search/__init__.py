"""Searching structures.

The GA with single parent mating, local search and its polish, forward selection,
certification by branch and bound.
"""
