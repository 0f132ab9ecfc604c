"""Signal handlers installed for the length of a `with` block (tcd.runner's deferred
interrupt of a run, and the other commands' SIGTERM taken as Ctrl-C)."""
from __future__ import annotations

import signal
import threading


class SignalScope:
    """While open, `_handler` handles each of `signals`, installed only in the main thread and
    only where the signal's default action is in force (Python's own handler for SIGINT,
    SIG_DFL for others): a process started with a signal ignored keeps ignoring it. The
    previous handlers come back on exit."""
    signals: tuple = ()

    def _handler(self, signum, frame):
        raise NotImplementedError

    def __enter__(self):
        self._old = {}
        if threading.current_thread() is threading.main_thread():
            for signum in self.signals:
                default = signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL
                if signal.getsignal(signum) == default:
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
