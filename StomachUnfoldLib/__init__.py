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


#: The Ctrl-C presses the command's handlers saw. Python drops what a handler raises inside a weakref callback (the
#: import system's module locks have one), and the run would go on to write its outputs: the command checks this
#: list before each stage and at each progress report, and cancels (``cli``).
CTRL_C: list = []


def cancelled_while_starting(signum, frame):
    """Ctrl-C while the ``stomach-unfold`` command is still importing: its one line and status 130, no traceback."""
    import sys

    CTRL_C.append(signum)
    try:
        sys.stderr.write("error: cancelled (Ctrl-C); no output was written\n")
    except OSError:
        pass
    raise SystemExit(130)


def _quiet_dropped_ctrl_c(unraisable):
    """``sys.unraisablehook`` of the command: a Ctrl-C that Python dropped (raised in a weakref callback) prints no
    traceback, as the command cancels at its next check (CTRL_C); anything else goes to Python's own hook."""
    import sys

    if CTRL_C and isinstance(unraisable.exc_value, (KeyboardInterrupt, SystemExit)):
        return
    sys.__unraisablehook__(unraisable)


def _starting_the_command() -> bool:
    import os
    import signal
    import sys

    return (bool(sys.argv) and os.path.basename(sys.argv[0]) == "stomach-unfold"
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler)


if _starting_the_command():  # the command, not a library import: cli.main() takes over from here
    import signal as _signal
    import sys as _sys

    _signal.signal(_signal.SIGINT, cancelled_while_starting)
    _sys.unraisablehook = _quiet_dropped_ctrl_c


def __getattr__(name):
    """``Volume``, ``ras_to_lps`` and ``lps_to_ras`` on first use: importing the package imports no NumPy, so the
    command line can catch a Ctrl-C from its first milliseconds."""
    if name in ("Volume", "ras_to_lps", "lps_to_ras"):
        from . import geometry

        return getattr(geometry, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
