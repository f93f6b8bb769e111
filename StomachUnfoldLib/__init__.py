"""StomachUnfoldLib: virtual unfolded views of the stomach from CT (Oda et al.), pure NumPy/SciPy.

Stages, one module each, in pipeline order:
``io`` (input/output), ``preprocessing`` (air and wall regions), ``centerline``, ``incision_line``,
``wall_model`` (hexahedral mass-spring-damper model), ``unfolding_force`` (unfolded plane, base line,
destination points), ``newmark`` (Newmark-beta integration and termination), ``unfolded_volume``,
``correspondence``; ``pipeline`` chains them and ``cli`` is the ``stomach-unfold`` command.
"""
from .errors import (StomachUnfoldError, InputError, PointError, AnatomyError,  # noqa: F401
                     SimulationError, Cancelled, OutputError)

__version__ = "0.1.0"


def __getattr__(name):
    """``Volume``, ``ras_to_lps`` and ``lps_to_ras`` on first use: importing the package imports no NumPy, so the
    command line can catch a Ctrl-C from its first milliseconds."""
    if name in ("Volume", "ras_to_lps", "lps_to_ras"):
        from . import geometry

        return getattr(geometry, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
