"""StomachUnfoldLib: virtual unfolded views of the stomach from CT (Oda et al.), pure NumPy/SciPy.

Stages, one module each, in pipeline order:
``io`` (input/output), ``preprocessing`` (air and wall regions), ``centerline``, ``incision_line``,
``wall_model`` (hexahedral mass-spring-damper model), ``unfolding_force`` (unfolded plane, base line,
destination points), ``newmark`` (Newmark-beta integration and termination), ``unfolded_volume``,
``correspondence``; ``pipeline`` chains them and ``cli`` is the ``stomach-unfold`` command.
"""
from .geometry import Volume, ras_to_lps, lps_to_ras  # noqa: F401
from .errors import (StomachUnfoldError, InputError, PointError, AnatomyError,  # noqa: F401
                     SimulationError, Cancelled)

__version__ = "0.1.0"
