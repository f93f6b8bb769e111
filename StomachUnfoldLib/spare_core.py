"""Work started beside the main thread on a spare core, to be used if it turns out to be needed.

The isometric method's map with light distance terms is needed only when the map with heavy ones folds a flap over
itself that the judge would count, which is known only once that map is done. Where the process has a second
core to itself, the light map starts at the same time as the heavy one (both are numpy and SuperLU work that runs
outside the interpreter lock) and is abandoned when it is not needed: the same result as running it after, in the
time of one. Work that is always used goes beside too (the scan of a CT on file while the modules load, the grade's
mucosa points during the method, the volume's and models' files while the view is drawn). Batch and benchmark
workers, which fill every core with runs of their own, turn all of it off (:data:`SPARE_CORES`): two threads of one
run on a core another run needs wait on each other for the interpreter lock (measured: a random stomach 10-20 %
slower with two such workers on two cores).
"""
from __future__ import annotations

import os
import signal
import threading
from contextlib import contextmanager

__all__ = ["SPARE_CORES", "spare_cores", "Beside", "signals_held"]

#: Whether a run may start work beside its main thread. None: where this process may run on two cores or more;
#: the batch and benchmark workers set False (each core has a run of its own).
SPARE_CORES: bool | None = None


def _cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def spare_cores() -> bool:
    """True when this process may start work beside the main thread (:data:`SPARE_CORES`, else two usable cores or
    more)."""
    return bool(SPARE_CORES) if SPARE_CORES is not None else _cores() > 1


@contextmanager
def signals_held():
    """Hold SIGINT, SIGTERM and SIGHUP (delivered when the block ends) where the platform allows."""
    held = {signal.SIGINT, signal.SIGTERM} | ({signal.SIGHUP} if hasattr(signal, "SIGHUP") else set())
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


class _Abandoned(Exception):
    """Raised inside abandoned work by its ``check()``: the block that started it has been left."""


class Beside:
    """``fn(*args, check=check)`` started in a thread on entering the block, when a core is spare.

    ``result()`` waits for it and returns its value or raises its exception; where nothing was started it runs
    ``fn`` here (so the result is the same either way). Leaving the block abandons the work: ``fn`` calls ``check()``
    between its steps and it raises once the block is left; the thread is joined before the block ends, so no work
    outlives it (a Cancel, a signal or an error in the main thread included). Work starts beside only where
    :func:`spare_cores`. With ``checked=False``, ``fn(*args)`` takes no ``check`` (work that is always used; an
    abandoned one runs to its end).
    """

    def __init__(self, fn, *args, checked: bool = True):
        self._fn, self._args = (fn, args) if checked else ((lambda *a, check: fn(*a)), args)
        self._stop = threading.Event()
        self._thread = None
        self._out = None

    def __enter__(self) -> "Beside":
        if not spare_cores():
            return self
        try:
            # started with the signals held (the thread keeps them held: they go to the main thread), so that a
            # signal is handled only once the thread is running and known here; one handled as they are let through
            # leaves __enter__ with an exception, and __exit__ would not run: the work is stopped and joined here
            with signals_held():
                self._thread = threading.Thread(target=self._run, name="stomach-unfold-beside", daemon=True)
                self._thread.start()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _check(self) -> None:
        if self._stop.is_set():
            raise _Abandoned

    def _run(self) -> None:
        try:
            self._out = (True, self._fn(*self._args, check=self._check))
        except BaseException as e:  # handed to result(); an abandoned run's _Abandoned is dropped with it
            self._out = (False, e)

    @property
    def started(self) -> bool:
        """Whether the work runs beside the main thread (False: result() runs it here)."""
        return self._thread is not None

    def result(self):
        """The work's return value (waiting for it, or running it here when it was not started)."""
        if self._thread is None:
            return self._fn(*self._args, check=lambda: None)
        self._thread.join()
        ok, value = self._out
        if not ok:
            raise value
        return value

    def __exit__(self, *exc) -> bool:
        self._stop.set()
        if self._thread is not None:
            try:
                self._thread.join()
            finally:  # a signal during the wait: the work stops at its next check; it is joined before going on
                self._thread.join()
        return False
