"""Errors the library raises on bad input or failed runs; each message says what to do next."""
from __future__ import annotations

__all__ = ["StomachUnfoldError", "InputError", "PointError", "AnatomyError", "SimulationError", "Cancelled",
           "OutputError"]


class StomachUnfoldError(Exception):
    """Base class of every documented error of the library (the command line exits 2 on these)."""


class InputError(StomachUnfoldError, ValueError):
    """The input file, volume or parameters cannot be used (wrong format, dimension, range, value)."""


class PointError(StomachUnfoldError, ValueError):
    """The cardia or pylorus point is missing, outside the volume or not near the stomach lumen."""


class AnatomyError(StomachUnfoldError):
    """The stomach lumen, wall or centreline could not be found from the input (e.g. no gas: use --mask)."""


class SimulationError(StomachUnfoldError):
    """The unfolding simulation diverged or produced no usable model."""


class Cancelled(StomachUnfoldError):
    """The run was cancelled by the user (progress callback, Cancel button or Ctrl-C)."""


class OutputError(StomachUnfoldError, OSError):
    """The outputs cannot be written: the output folder is missing, not a folder, read-only, full or holds an input."""
