"""Signal handlers installed for the length of a `with` block (tcd.runner's deferred
interrupt of a run, and the other commands' SIGTERM taken as Ctrl-C)."""
from __future__ import annotations

import errno
import os
import signal
import sys
import threading

#: the signals that stop a run at the end of its step, and that a `--jobs` worker notes:
#: Ctrl-C, `kill`, and the hang-up of the terminal it runs in (SIGHUP: a closed terminal or
#: SSH session; where the platform has it). SIGHUP used to end a run at once, losing up to
#: checkpoint_every_s of work (session 70's probe).
STOP_SIGNALS = tuple(s for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None))
                     if s is not None)
#: the same, less Ctrl-C: what other commands take as Ctrl-C (TermAsInterrupt)
END_SIGNALS = STOP_SIGNALS[1:]

#: a `tcd run --jobs` worker process (`enter_worker`): it stops taking samples once told to stop
in_worker = False
#: set in a worker only (note_stop, runner.DeferredInterrupt): a STOP_SIGNALS signal has come
#: (during a sample or between two): the samples still queued for it do not start (a stopped
#: run left them to its resume)
stop_requested = False


#: in a worker: the run's stop (a multiprocessing Event its parent sets), or None
stop_event = None


def stopping() -> bool:
    """In a worker: whether the run was told to stop (a signal it saw, or its parent's)."""
    return stop_requested or (stop_event is not None and stop_event.is_set())


class StartupBlocked:
    """While open, and after until `release` (the parent of `tcd run --jobs` starting its
    worker processes), the stop signals are blocked in this thread: one that comes meanwhile
    waits, and is delivered at `release`; the workers, which inherit the block (a signal mask outlives
    fork and exec), cannot be killed before their initializer has put their own handler in
    place and lifted it (`enter_worker`). Where the platform has no signal masks, nothing."""

    def __enter__(self):
        self._old = None
        if hasattr(signal, "pthread_sigmask") and \
                threading.current_thread() is threading.main_thread():
            self._old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
        return self

    def release(self) -> None:
        """Lift the block (once): a signal that came meanwhile is delivered now, to this
        process's handler (the caller lifts it where that handler's effect is taken care of:
        a KeyboardInterrupt inside its `try`)."""
        if self._old is not None:
            old, self._old = self._old, None
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

    def __exit__(self, *exc):
        if exc[0] is not None:          # the block ends with an error: lifted now
            self.release()
        return False


def note_stop(signum, frame):
    """A worker's handler for SIGINT and SIGTERM between its samples: remember the request
    (`stop_requested`) and live on, so that its pool is not broken and the samples still
    queued end at once, not started (the run's parent collects them)."""
    global stop_requested
    stop_requested = True


def enter_worker() -> None:
    """Mark this process as a `tcd run --jobs` worker and install `note_stop` for SIGINT and
    SIGTERM where their default action is in force (a signal ignored stays ignored), then lift
    the block of the stop signals it was started with (StartupBlocked: one that came while it
    started is delivered now, to `note_stop`). A sample's own handler
    (runner.DeferredInterrupt) replaces it while the sample runs."""
    global in_worker
    in_worker = True
    if threading.current_thread() is threading.main_thread():
        for signum in STOP_SIGNALS:
            if signal.getsignal(signum) == _default(signum):
                signal.signal(signum, note_stop)
        if hasattr(signal, "pthread_sigmask"):
            signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


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
    """SIGTERM (`kill PID`, `timeout`, a batch scheduler) or SIGHUP (its terminal closed)
    raises KeyboardInterrupt, as Ctrl-C does, so that a command other than `tcd run` (export,
    figures, render, analyse, ...) stops through its `finally` blocks: the file it was writing
    is removed (io.atomic_path) instead of being left as a temporary beside its outputs.
    Installed as SignalScope says."""
    signals = END_SIGNALS

    def _handler(self, signum, frame):
        raise KeyboardInterrupt


#: what a report stream's write fails with once its reader is gone: the pipe's reader ended
#: (`tcd run ... | head -1`), the terminal was closed (EIO once a closed terminal's process
#: lives on: SIGHUP ignored, as under `nohup` without its redirection)
GONE = (errno.EPIPE, errno.EIO)


class ReportStream:
    """sys.stdout or sys.stderr of a `tcd run` (and of its `--jobs` workers): a write or flush
    that fails because the reader is gone (GONE) points the stream's file descriptor at
    os.devnull, drops the text and lets the run go on: a run's products are its files, its
    report on the terminal is not. A run that met a gone reader used to stop: at Taichi's
    banner with status 0, having run nothing (`| head -1`), or, its terminal closed, at its
    next progress line, or at its last line with status 74 (session 70's probe). `lost` is
    the first such error (None while the reader is there). Other errors (a full disk under a
    redirection) are raised as before."""

    def __init__(self, stream):
        self._stream = stream
        self.lost = None

    def write(self, text):
        try:
            return self._stream.write(text)
        except OSError as exc:
            self._lose(exc)
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except OSError as exc:
            self._lose(exc)

    def _lose(self, exc: OSError) -> None:
        if exc.errno not in GONE:
            raise exc
        if self.lost is None:
            self.lost = exc
            try:
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, self._stream.fileno())
                os.close(devnull)
            except (OSError, ValueError):           # no descriptor: write into nothing
                self._stream = open(os.devnull, "w", encoding="utf-8")
        try:
            self._stream.flush()            # what it held goes to os.devnull now
        except OSError:
            pass

    def __getattr__(self, name):
        return getattr(self._stream, name)


def guard_report_streams() -> None:
    """Wrap sys.stdout and sys.stderr in ReportStream (once). Taichi, imported after, would
    take a sys.stdout other than sys.__stdout__ for a notebook's and print after every kernel
    launch (its "Graphical python shell detected" buffer): TI_ENABLE_PYBUF=0 unless set."""
    os.environ.setdefault("TI_ENABLE_PYBUF", "0")
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if stream is not None and not isinstance(stream, ReportStream):
            setattr(sys, name, ReportStream(stream))
