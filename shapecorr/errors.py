"""Exception hierarchy of shapecorr.

Every error caused by bad input (a file, a folder, a config value) is a :class:`ShapeCorrError`
subclass whose message names the offending file (when there is one) and the problem. The command-line
entry points catch :class:`ShapeCorrError`, print its message without a traceback and exit non-zero.
"""

from __future__ import annotations

from os import PathLike


class ShapeCorrError(Exception):
    """Base class of all errors raised deliberately by shapecorr.

    Parameters
    ----------
    message
        What is wrong, in words a user can act on.
    path
        The file or folder the problem is about, if any; it is prefixed to the message.
    """

    def __init__(self, message: str, path: str | PathLike | None = None):
        self.path = None if path is None else str(path)
        self.problem = message
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)


class MeshReadError(ShapeCorrError):
    """A mesh file is missing, unreadable, empty or of an unknown format."""


class InvalidMeshError(ShapeCorrError):
    """A mesh was read but its content is invalid.

    E.g. NaN/Inf coordinates, bad face indices, degenerate faces, unreferenced vertices.
    """


class CorrespondenceError(ShapeCorrError):
    """A correspondence file (.vts, .map, .txt) is unreadable or inconsistent with its shapes."""


class DatasetError(ShapeCorrError):
    """A dataset folder is missing, empty, or its layout / split files are inconsistent."""


class CacheError(ShapeCorrError):
    """A cache entry cannot be written or read (a corrupt entry is rebuilt, not raised)."""


class NumericalError(ShapeCorrError):
    """A computation produced NaN/Inf or failed to converge."""


class ConfigError(ShapeCorrError):
    """A configuration value is invalid or inconsistent."""
