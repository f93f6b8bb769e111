"""Progress reporting and cancellation shared by all stages."""
from __future__ import annotations

from typing import Callable, Optional

from .errors import Cancelled

__all__ = ["ProgressCallback", "Progress"]

#: ``callback(stage, fraction)``: stage name and fraction done in [0, 1]; return ``False`` to cancel.
ProgressCallback = Callable[[str, float], Optional[bool]]


class Progress:
    """Wraps a user callback: ``report(stage, fraction)`` forwards it and raises Cancelled if asked to stop.

    ``sub(stage, lo, hi)`` gives a reporter that maps its own [0, 1] onto [lo, hi] of the whole run,
    so a stage can report its own progress without knowing its share of the pipeline.
    """

    def __init__(self, callback: ProgressCallback | None = None, lo: float = 0.0, hi: float = 1.0,
                 stage: str = ""):
        self.callback = callback
        self.lo, self.hi, self.stage = lo, hi, stage

    def report(self, stage: str | None = None, fraction: float = 0.0) -> None:
        """Report progress of ``stage`` (fraction in [0, 1] of this reporter's span); raise Cancelled on request."""
        if self.callback is None:
            return
        f = self.lo + (self.hi - self.lo) * min(max(float(fraction), 0.0), 1.0)
        if self.callback(stage or self.stage, f) is False:
            raise Cancelled(f"cancelled during {stage or self.stage or 'the run'}")

    def sub(self, stage: str, lo: float, hi: float) -> "Progress":
        """Reporter for one stage spanning [lo, hi] of this reporter's range."""
        span = self.hi - self.lo
        return Progress(self.callback, self.lo + span * lo, self.lo + span * hi, stage)

    def __call__(self, fraction: float) -> None:
        """Shorthand for ``report(self.stage, fraction)``."""
        self.report(self.stage, fraction)
