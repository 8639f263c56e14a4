"""The model.

Candidate terms, the NARX model and its document, several outputs, simulation,
uncertainty, segments.
"""
