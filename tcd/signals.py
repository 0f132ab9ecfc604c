"""Signal handlers installed for the length of a `with` block (tcd.runner's deferred
interrupt of a run, and the other commands' SIGTERM taken as Ctrl-C)."""
from __future__ import annotations

import signal
import threading

#: a `tcd run --jobs` worker process (`enter_worker`): it stops taking samples once told to stop
in_worker = False
#: set in a worker only (note_stop, runner.DeferredInterrupt): a SIGINT or SIGTERM has come
#: (during a sample or between two): the samples still queued for it do not start (a stopped
#: run left them to its resume)
stop_requested = False


def note_stop(signum, frame):
    """A worker's handler for SIGINT and SIGTERM between its samples: remember the request
    (`stop_requested`) and live on, so that its pool is not broken and the samples still
    queued end at once, not started (the run's parent collects them)."""
    global stop_requested
    stop_requested = True


def enter_worker() -> None:
    """Mark this process as a `tcd run --jobs` worker and install `note_stop` for SIGINT and
    SIGTERM where their default action is in force (a signal ignored stays ignored). A
    sample's own handler (runner.DeferredInterrupt) replaces it while the sample runs."""
    global in_worker
    in_worker = True
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(signum) == _default(signum):
                signal.signal(signum, note_stop)


def _default(signum):
    return signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL


class SignalScope:
    """While open, `_handler` handles each of `signals`, installed only in the main thread and
    only where the signal's default action is in force (Python's own handler for SIGINT,
    SIG_DFL for others; in a `--jobs` worker, `note_stop`): a process started with a signal
    ignored keeps ignoring it. The previous handlers come back on exit."""
    signals: tuple = ()

    def _handler(self, signum, frame):
        raise NotImplementedError

    def __enter__(self):
        self._old = {}
        if threading.current_thread() is threading.main_thread():
            for signum in self.signals:
                if signal.getsignal(signum) in (_default(signum), note_stop):
                    self._old[signum] = signal.signal(signum, self._handler)
        return self

    def __exit__(self, *exc):
        for signum, old in self._old.items():
            signal.signal(signum, old)
        self._old = {}
        return False


class TermAsInterrupt(SignalScope):
    """SIGTERM (`kill PID`, `timeout`, a batch scheduler) raises KeyboardInterrupt, as Ctrl-C
    does, so that a command other than `tcd run` (export, figures, render, analyse, ...) stops
    through its `finally` blocks: the file it was writing is removed (io.atomic_path) instead of
    being left as a temporary beside its outputs. Installed as SignalScope says."""
    signals = (signal.SIGTERM,)

    def _handler(self, signum, frame):
        raise KeyboardInterrupt
