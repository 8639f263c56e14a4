"""The errors a user can cause, at the bottom of the package: every layer raises these.

Each is a ``ValueError`` with a message a user can act on; the command line
prints it as one ``error: ...`` line, the node as a refusal with the reason.
"""

from __future__ import annotations

__all__ = [
    "BagError",
    "DataError",
    "FieldPathError",
    "FileCheckError",
    "MemoryLimitError",
    "MissingDependencyError",
    "ModelFormatError",
    "SettingsError",
    "TooFewSamplesError",
]


class DataError(ValueError):
    """Input data that cannot be used, with a message a user can act on."""


class TooFewSamplesError(DataError):
    """Fewer samples (or regression rows) than the identification needs."""


class BagError(DataError):
    """A bag that cannot be written or read as asked."""


class FieldPathError(ValueError):
    """A field path that is malformed or does not fit a message."""


class ModelFormatError(ValueError):
    """A model document that cannot be read (wrong schema, version or content)."""


class FileCheckError(ValueError):
    """A destination that cannot be written, with the reason."""


class MemoryLimitError(ValueError):
    """An input or a matrix would need more memory than the bound allows."""


class SettingsError(ValueError):
    """A setting with a wrong type or a value out of range, named in the message."""


class MissingDependencyError(ImportError):
    """A required library is missing or broken; the message says which and how to fix it."""
