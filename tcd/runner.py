"""Run a scenario: samples (one per seed) through their stages, with outputs and checkpoints.

Layout of an output directory:
    scenario.toml              copy of the scenario text (written when the run starts; a
                               --resume must bring the same scenario: record_scenario)
    run.json                   the backend the run started on (arch, precision), tcd's version,
                               the scenario file and the seeds it started with
    summary.json               headline numbers of the whole run (written at the end)
    sample_<seed>/states.h5    snapshots (every `output.snapshot_every` s of simulated time)
    sample_<seed>/<stage>_series.h5 (+ .csv)   per-step series of each stage
    sample_<seed>/prepared.h5  the prepared sample (checkpoint format), loaded by the shear stage
    sample_<seed>/checkpoint.h5  latest checkpoint (every `output.checkpoint_every_s` s of wall time)
    sample_<seed>/summary.json   the sample's numbers per stage
    batch_checkpoint.h5        with `run_batch` (tcd run --batch), the one checkpoint of the batch
Every file is replaced atomically (tcd.io). `resume=True` continues each unfinished sample from
its checkpoint; because phases, snapshot times and settle checks depend only on the simulation
state and step counts, the resumed run ends with the same numbers as an uninterrupted one.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import os
import pathlib
import shlex
import signal
import socket
import sys
import threading
import time
import warnings

import numpy as np

from . import __version__, backend, io
from . import observables as obs
from .config import text_settings
from .state import MAX_SYSTEMS
from .observables import PAPER_EXPERIMENT, PAPER_SIMULATION
from .protocols import PREPARE_PHASES, PROTOCOLS, SETTLE_CHECK_EVERY, Phase, settled
from . import signals as worker_signals
from .signals import SignalScope

FRAME_KEYS = ("particles/x", "particles/v", "particles/w", "particles/radius", "particles/layer",
              "walls/kind", "walls/point", "walls/direction", "walls/radius", "walls/extent",
              "walls/force", "contacts/i", "contacts/j", "contacts/impulse", "contacts/gap",
              "bonds/i", "bonds/j", "bonds/state", "bonds/impulse", "bonds/broken_time")


def frame_of(sim) -> dict:
    d = sim.state_dict()
    f = {k: d[k] for k in FRAME_KEYS}
    if "bonds/turn" in d:       # bond_frame = "end": the whole impulse the bond gave
        f["bonds/impulse"] = d["bonds/impulse"] + d["bonds/turn"]
    f["bonds/broken_position"] = d["bonds/broken_pos"]
    if "particles/sample_index" in d:       # a renumbered shear: each particle's sample index
        f["particles/sample_index"] = d["particles/sample_index"]
    return f


class Progress:
    """A tqdm bar on a terminal, plain log lines (every 10 s) otherwise. The run updates it
    every 100th step, and sooner when `due` says so (steps of seconds each). The first update
    gives the step the phase starts from (more than 0 after --resume): rates and the time left
    count only the steps made since, so a resumed run shows its own speed. A log line also
    gives the rate and the mean sweeps per step since the line before (the steps' sweeps
    given to count_sweeps), and the time left at the mean rate and at that last rate: the rate
    since the start includes the compiling, and a bond cascade near the peak runs tens to
    hundreds of times slower than the mean (neither rate alone tells when it ends)."""

    def __init__(self, enabled: bool, label: str, total: int, h: float):
        self.enabled, self.label, self.total, self.h = enabled, label, total, h
        self.tty = enabled and sys.stderr.isatty()
        self.bar = None
        self.first = None          # the step of the first update
        self.t0 = self.last = time.perf_counter()    # `last`: the last log line (or bar update)
        self.done = 0
        self.last_step = 0         # the step of the last log line
        self.sweeps, self.counted = 0, 0       # sweeps summed since then, over `counted` steps

    def count_sweeps(self, sweeps: int) -> None:
        """One step's sweeps, for the next log line's mean."""
        self.sweeps += sweeps
        self.counted += 1

    def due(self) -> bool:
        """Whether an update is due before the next 100th step: 10 s since the last log line
        (1 s since the bar's last update on a terminal). A bond cascade at a tight tolerance
        takes 10 s a step, and a log updated only every 100th step would say nothing for a
        quarter of an hour."""
        return (self.enabled and self.first is not None
                and time.perf_counter() - self.last >= (1.0 if self.tty else 10.0))

    def update(self, step: int, sim_time: float, extra: str = "") -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if self.first is None:
            self.first, self.done, self.t0, self.last = step, step, now, now
            self.last_step = step
            if self.tty:
                from tqdm import tqdm
                self.bar = tqdm(total=self.total, initial=step, desc=self.label, unit="step",
                                dynamic_ncols=True, leave=False)
        n = step - self.done
        self.done = step
        if self.bar is not None:
            self.last = now
            self.bar.update(n)
            self.bar.set_postfix_str(f"t={sim_time:.4f}s {extra}", refresh=False)
            return
        if now - self.last >= 10.0:
            rate = (step - self.first) / max(now - self.t0, 1e-9)
            left = (self.total - step) / rate if rate > 0 else float("nan")
            recent, left_recent = "", ""
            if step > self.last_step and self.last_step > self.first:
                lately = (step - self.last_step) / max(now - self.last, 1e-9)
                recent = f" ({lately:.1f} over the last {step - self.last_step} steps"
                if self.counted:
                    recent += f", {self.sweeps / self.counted:.1f} sweeps per step"
                recent += ")"
                # a bond cascade slows a run tens to hundreds of times (at 1e-7 for hours):
                # the mean rate alone would promise minutes
                left_recent = f", {(self.total - step) / lately / 60:.1f} at the last lines' rate"
            self.last, self.last_step = now, step
            self.sweeps, self.counted = 0, 0
            print(f"[tcd] {self.label}: step {step}/{self.total} t={sim_time:.4f} s "
                  f"{rate:.1f} steps/s{recent}, {left / 60:.1f} min left at the mean rate"
                  f"{left_recent} {extra}",
                  file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


#: how long (s) a stopped `--jobs` run waits for each worker to end on its own (its running
#: sample checkpointed at the end of its step) before the pool is shut down
STOP_WAIT_S = 300.0


def check_run_settings(scenario, jobs: int, pending) -> None:
    """What refuses a run of `scenario` with `jobs` processes over the seeds `pending` before
    anything is written: more partitioned solver threads than cores, a backend that is not
    there. (`tcd run --from` checks it before it writes the new run's folder: a refusal left
    that folder behind, and a second try was refused for it: session 72's review.)"""
    if jobs > 1 and len(pending) > 1 and scenario.solver.schedule == "partitioned":
        threads = min(jobs, len(pending)) * scenario.solver.threads
        cores = os.cpu_count() or 1
        if threads > cores:
            raise ValueError(
                f"--jobs {jobs} with [solver] threads = {scenario.solver.threads} runs {threads} "
                f"solver threads on {cores} cores: the partitioned schedule's threads wait for "
                f"each other actively and must not share cores; use --jobs "
                f"{max(1, cores // scenario.solver.threads)}, fewer threads, or schedule = \"serial\"")
    backend.check_available(scenario.backend.arch)     # before anything is written


def run_scenario(scenario, out_dir, *, resume: bool = False, progress: bool = True,
                 jobs: int = 1) -> dict:
    """Run every sample of `scenario` into `out_dir`; returns the summary.

    jobs > 1 runs that many samples at once, each in its own process (the CPU solver uses one
    core per sample, so a 2-core machine prepares and shears two samples in the time of one).
    Each sample's numbers depend on its seed, not on `jobs`: a worker with one core runs the
    kernels' loops inline, a single run on several cores in the pool (backend.loop_mode,
    recorded as `cpu_loops` in its summary), and with Taichi's fast math off (the CPU's
    default) the two agree bit for bit. With fast math on (TCD_FAST_MATH=1) they differ in the
    last bits, which a bond cascade can amplify."""
    out = pathlib.Path(out_dir)
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if resume:
        check_resumable_samples(out, scenario.seeds)
        progressed = out.is_dir() and (any(out.glob("sample_*/checkpoint.h5"))
                                       or any(out.glob("sample_*/summary.json")))
        if not progressed:
            if (out / "batch_checkpoint.h5").is_file():
                raise FileNotFoundError(f"{out}: this run was started with --batch (it has a "
                                        "batch_checkpoint.h5): resume it with --batch --resume")
            if not _stopped_before_first_checkpoint(out):
                raise FileNotFoundError(f"{out}: nothing to resume (no checkpoint found)")
            # a fresh run is refused there (it holds results): every sample starts over
            print(f"tcd: note: {out}: no checkpoint yet (the run stopped before its first, "
                  "or its sample folders were moved away): every sample starts from the "
                  "beginning", file=sys.stderr)
    t_start = time.perf_counter()
    done = {}
    for seed in scenario.seeds:
        path = out / f"sample_{seed}" / "summary.json"
        if resume and path.exists():
            done[seed] = json.loads(path.read_text())
    pending = [seed for seed in scenario.seeds if seed not in done]
    if resume and not pending:
        print(f"tcd: note: {out}: every sample was already done; nothing to resume (the run's "
              "summary is written again)", file=sys.stderr)
    check_run_settings(scenario, jobs, pending)
    # every sample a shear starts from is read before anything is written or run (a resumed
    # sample with a checkpoint has its state there)
    check_samples(scenario, [seed for seed in pending if not (
        resume and (out / f"sample_{seed}" / "checkpoint.h5").is_file())])
    with recorded_run(scenario, out, resume):
        if jobs > 1 and len(pending) > 1:
            import concurrent.futures
            import multiprocessing
            ctx = multiprocessing.get_context("spawn")      # a fresh Taichi runtime per process
            workers = min(jobs, len(pending))
            # each worker's share of the cores (its solver's threads for the partitioned schedule):
            # one thread runs its kernels' loops inline (backend.serial_loops): with fast math
            # off (the CPU's default) the numbers of a run in the pool too; with TCD_FAST_MATH=1
            # they differ in the last bits (loop_mode)
            if scenario.solver.schedule == "partitioned":
                worker_threads = scenario.solver.threads
            else:
                worker_threads = max(1, (os.cpu_count() or 1) // workers)
            for seed in pending:        # a worker orphaned by a killed run may still write
                with run_lock(out / f"sample_{seed}"):      # there: refuse before any starts
                    pass
            # the run's stop, seen by every worker (a worker still starting when the signal
            # came did not see it)
            stop = ctx.Event()
            # the workers start with the stop signals blocked, until their initializer has
            # put their own handler in place: a Ctrl-C or SIGTERM in the seconds a worker takes
            # to start killed it, the pool broke, and the run ended in a traceback or waited
            # for ever on a worker that the pool's SIGTERM could not end (session 72's review)
            # (ForwardTerm first: the block holds in this thread only, and a SIGTERM that
            # another thread of this process takes must not find its default action)
            with ForwardTerm(None, stop) as forward:
                with worker_signals.StartupBlocked() as blocked:
                    pool = concurrent.futures.ProcessPoolExecutor(
                        max_workers=workers, mp_context=ctx, initializer=_watch_parent,
                        initargs=(os.getpid(), stop))
                    forward.pool = pool
                    try:
                        futures = {seed: pool.submit(_sample_job, scenario.text,
                                                     scenario.source, scenario.backend.arch,
                                                     scenario.backend.precision, seed,
                                                     str(out / f"sample_{seed}"), resume,
                                                     progress, worker_threads)
                                   for seed in pending}
                    except BaseException:
                        stop.set()
                        pool.shutdown(wait=True, cancel_futures=True)
                        raise
                with pool:
                    try:
                        blocked.release()       # a signal that came meanwhile lands here
                        for seed, future in futures.items():
                            done[seed] = future.result()
                    except (KeyboardInterrupt, concurrent.futures.process.BrokenProcessPool) \
                            as exc:
                        # stopped (Ctrl-C, SIGTERM): the samples not handed to a worker yet
                        # are dropped, a sample queued in a worker ends at once, not started
                        # (_sample_job), and the running ones checkpoint and stop; their
                        # resume runs them all. A sample queued used to start once a worker
                        # was free, the parent waiting for it to the end (session 60).
                        stopped = stop.is_set() or isinstance(exc, KeyboardInterrupt)
                        stop.set()
                        # each worker ends once idle (_watch_parent): waited for here, so
                        # that one still starting is not left without the pool's queues (a
                        # traceback of its start-up, the parent gone: session 72)
                        for proc in list((getattr(pool, "_processes", None) or {}).values()):
                            proc.join(timeout=STOP_WAIT_S)
                        pool.shutdown(wait=True, cancel_futures=True)
                        if stopped:
                            raise KeyboardInterrupt from None
                        raise ValueError(
                            f"a --jobs worker process ended abruptly (killed, or out of "
                            f"memory?): {str(exc).rstrip('.')}; the other samples stopped at a "
                            "checkpoint: resume the run with --resume") from None
        else:
            backend.init(scenario.backend.arch, scenario.backend.precision)
            for seed in pending:
                done[seed] = run_sample(scenario, seed, out / f"sample_{seed}", resume=resume,
                                        progress=progress)
        samples = [done[seed] for seed in scenario.seeds]
        if resume:      # a study split across invocations into one folder (--seeds): all of it
            others = _finished_samples(out, exclude=scenario.seeds)
            if others:
                samples = sorted(samples + others, key=lambda smp: smp["seed"])
        summary = summarize(scenario, samples)
        summary["wall_time_s"]["total_this_invocation"] = time.perf_counter() - t_start
        summary["jobs"] = jobs
        io.write_json(out / "summary.json", summary)
        return summary


#: what a sample's folder holds once one of its stages has ended; its checkpoint is written
#: before them (_run_sample), so a folder that holds them and no checkpoint has lost it
STAGE_RESULTS = ("prepared.h5", "*_series.h5", "*_series.csv")
#: the tcd files an unfinished sample's resume goes on from or keeps as its results
RESUMED_FILES = ("checkpoint.h5", "states.h5", "prepared.h5", "*_series.h5")


def check_resumable_samples(out: pathlib.Path, seeds) -> None:
    """Before a resume writes anything: refuse, naming the file, an unfinished sample of
    `seeds` whose checkpoint.h5 is gone while the results of a stage are there (its resume
    started the sample over and overwrote them: session 70's probe), or one of whose files
    (RESUMED_FILES) cannot be read whole (a damaged checkpoint stopped the resume with a
    traceback; a damaged states.h5 or prepared.h5 was kept unreadable, the run ending with
    status 0). A sample folder moved away runs again from the start."""
    for seed in seeds:
        d = out / f"sample_{seed}"
        if not d.is_dir() or (d / "summary.json").exists():
            continue
        if not (d / "checkpoint.h5").exists():
            results = sorted({p.name for pattern in STAGE_RESULTS for p in d.glob(pattern)})
            if results:
                raise ValueError(
                    f"{d / 'checkpoint.h5'} is missing, yet the sample holds the results of a "
                    f"stage ({', '.join(results)}): a resume cannot tell where it stopped, and "
                    "running it from the start would overwrite them; put its checkpoint back, "
                    f"or move {d} away to run that sample again from the start")
        for path in sorted({p for pattern in RESUMED_FILES for p in d.glob(pattern)}):
            if path.is_file():
                check_whole(path, f"move {d} away to run that sample again from the start")


def check_whole(path: pathlib.Path, remedy: str) -> None:
    """io.check_readable(path), its refusal ending with what a resume cannot do and `remedy`."""
    try:
        io.check_readable(path)
    except ValueError as exc:
        raise ValueError(f"{exc}: a resume cannot go on from it or keep it; restore it from a "
                         f"copy, or {remedy}") from None


def _stopped_before_first_checkpoint(out: pathlib.Path) -> bool:
    """Whether `out` holds a run that stopped before its first checkpoint (a kill in its
    first minute, or while a batch was built): its records (scenario.toml) and no checkpoint,
    batched or not, nor any summary. Its --resume starts over."""
    return ((out / "scenario.toml").is_file() and not (out / "batch_checkpoint.h5").exists()
            and not any(out.glob("sample_*/checkpoint.h5"))
            and not any(out.glob("**/summary.json")))


def _scenario_record(scenario) -> dict:
    """What a resumed run must share with the run it continues: the whole configuration but
    the seeds (a sample's numbers depend on its seed only), the description, the file's
    text and path (the backend is checked against run.json) and the wall-clock spacing of
    the checkpoints (`output.checkpoint_every_s`, which changes no number or frame)."""
    return scenario.model_dump(mode="json", by_alias=True, exclude={
        "text": True, "source": True, "seeds": True, "backend": True, "description": True,
        "output": {"checkpoint_every_s"}})


def scenario_changes(text: str, scenario, where: str) -> list:
    """How `scenario` differs from the scenario of TOML `text` (read from `where`: a run's
    scenario.toml or a checkpoint) in what a resumed run must share with the run it continues;
    ValueError naming `where` if the text is not a valid scenario."""
    from .config import ScenarioError, parse_scenario
    try:
        # the new scenario's source: relative sample paths resolve as they did
        first = parse_scenario(text, scenario.source, seeds=scenario.seeds)
    except ScenarioError as exc:
        reasons = "; ".join(f"{k}: {r}" if k else r for k, r in exc.problems)
        raise ValueError(f"{where}: the scenario this run started with cannot be read back "
                         f"({reasons}); resume is refused") from None
    return io.differences(_scenario_record(first), _scenario_record(scenario), base=1)


LOCK_FILE = ".tcd.lock"



class RunLocked(ValueError):
    """Another process holds the run directory's lock (run_lock)."""

@contextlib.contextmanager
def run_lock(out: pathlib.Path):
    """Hold `out`/.tcd.lock (an exclusive `flock`, created with `out` if need be) while a run
    writes into `out`: a second `tcd run` into the same directory, typically a `--resume` while
    the first process still runs, would append to the same states.h5 and overwrite the same
    checkpoint. It is refused, naming the process that holds the lock. The kernel drops the
    lock when its process ends, however it ends (a SIGKILL too), so a stale lock file never
    blocks a resume. Where `flock` is missing (not POSIX) or refused by the file system (some
    network file systems), the run goes on unlocked, with a warning."""
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:
        warnings.warn(f"{out}: no file locking on this platform; make sure that no other tcd "
                      "process writes into this directory", RuntimeWarning, stacklevel=3)
        yield
        return
    path = out / LOCK_FILE
    with open(path, "a+", encoding="utf-8") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            locked = True
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "a process that did not say which"
            raise RunLocked(f"{out}: another tcd run is writing into this directory ({holder}); "
                             "wait for it to end, or stop it (Ctrl-C or SIGTERM: it writes its "
                             "checkpoint) before --resume, or choose another --out "
                             "directory") from None
        except OSError as exc:
            warnings.warn(f"{path}: cannot lock ({exc}); make sure that no other tcd process "
                          "writes into this directory", RuntimeWarning, stacklevel=3)
            locked = False
        if locked:
            f.seek(0)
            f.truncate()
            f.write(f"pid {os.getpid()} on {socket.gethostname()}, since "
                    f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n")
            f.flush()
        yield


@contextlib.contextmanager
def recorded_run(scenario, out: pathlib.Path, resume: bool):
    """`record_scenario` under the run's lock (`run_lock`), held for the body: one process
    writes into `out` at a time. A resume's checks come before the lock is taken, so that a
    refused resume writes nothing, not even the lock file. A new run refused once its records
    were written (a sample's simulation cannot be built: two grains at one centre, a grid too
    large) takes its records back (`_take_back_records`); an interrupted one keeps them, so
    that it can be resumed."""
    if resume:
        record_scenario(scenario, out, resume)
    before = None if resume else _paths_in(out)       # None too when `out` is new
    locked = False
    try:
        with run_lock(out):
            locked = True
            try:
                if not resume:
                    record_scenario(scenario, out, resume)
                else:       # what writes killed hard left (each sample's folder: _run_sample)
                    _note_removed(io.remove_stale_temporaries(out))
                yield
            except Exception as exc:
                if not resume:      # under the lock: no other run writes into `out` now
                    _mark_taken_back(exc, _take_back_records(out, before))
                raise
    except RunLocked:
        # another run holds `out`: what was added since `before` is that run's (its records,
        # made since this one looked), not this one's; they were taken back (session 70)
        raise
    except Exception as exc:
        if not resume and not locked:       # the lock could not be made: `out` as it was
            _mark_taken_back(exc, _take_back_records(out, before))
        raise


#: what a new run writes before its samples run: its records and its lock (and a lock in each
#: sample's folder)
RECORD_FILES = ("scenario.toml", "run.json", LOCK_FILE)


def _paths_in(out: pathlib.Path) -> set | None:
    """Every path under `out` (None when `out` does not exist)."""
    return set(out.rglob("*")) if out.exists() else None


def _mark_taken_back(exc: BaseException, taken_back: bool) -> None:
    """Tell the command's error report (`cli._io_error`) that the failed run's records were
    taken back: nothing of it is left to resume."""
    if taken_back:
        try:
            exc.tcd_records_taken_back = True
        except AttributeError:      # an exception class without a __dict__
            pass


def _take_back_records(out: pathlib.Path, before: set | None) -> bool:
    """After a new run failed: when what it added to `out` (the paths not in `before`, None
    when `out` did not exist) is nothing but its records, locks and empty folders (no sample
    wrote anything, or what it wrote was removed by someone else), remove them, and `out`
    itself if the run created it, so that the refusal leaves the directory as it was. A run
    that wrote anything else keeps it all. True when it removed something."""
    if not out.is_dir():            # the failure was to make it
        return False
    try:
        added = sorted(_paths_in(out) - (before or set()), key=lambda q: len(q.parts),
                       reverse=True)
        if any(not q.is_dir() and q.name != LOCK_FILE
               and (q.parent != out or q.name not in RECORD_FILES) for q in added):
            return False
        for q in added:
            q.rmdir() if q.is_dir() else q.unlink()
        if before is None:
            out.rmdir()
        return bool(added) or before is None
    except OSError:         # another process writes there now: leave it all
        return False


def _note_removed(paths) -> None:
    if paths:
        print(f"tcd: note: removed {len(paths)} temporary file(s) that an interrupted write left "
              f"({', '.join(str(p) for p in paths[:3])}{', ...' if len(paths) > 3 else ''})",
              file=sys.stderr)


def record_scenario(scenario, out: pathlib.Path, resume: bool) -> None:
    """A new run: create `out` and keep the scenario's text (scenario.toml) and backend
    (run.json). A resumed one: refuse, before anything is written, a scenario or backend other
    than those the run started with (its samples would mix two configurations); the records
    are left as they are."""
    backend_now = {"arch": scenario.backend.arch, "precision": scenario.backend.precision,
                   "fast_math": backend.fast_math_setting(scenario.backend.arch)}
    stored = out / "scenario.toml"
    if resume and not stored.is_file():
        raise ValueError(f"{stored} is missing: a resumed run checks that it continues with the "
                         "scenario it started with; put that scenario back there (the run's "
                         "checkpoints are checked against it too), or start a new run in "
                         "another --out directory")
    if resume:
        try:
            text = stored.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{stored}: the scenario this run started with cannot be read "
                             f"back ({exc}); resume is refused") from None
        changed = scenario_changes(text, scenario, str(stored))
        record = out / "run.json"
        if record.is_file():
            try:
                started = json.loads(record.read_text())
                if not isinstance(started, dict):
                    raise ValueError("not a JSON object")
            except (OSError, ValueError) as exc:
                raise ValueError(f"{record}: the backend this run started with cannot be read "
                                 f"back ({exc}); resume is refused") from None
            changed += [f"backend.{k}: {started[k]!r} -> {v!r} (--{k})"
                        for k, v in backend_now.items()
                        if k != "fast_math" and k in started and started[k] != v]
            # fast math (TCD_FAST_MATH) changes the numbers' last bits; runs started before
            # session 33 did not record it and had it on, unless TCD_FAST_MATH said otherwise
            if "fast_math" in started:
                was = started["fast_math"]
            elif os.environ.get(backend.FAST_MATH_ENV, "").strip():
                was = backend_now["fast_math"]      # the user's explicit choice stands
            else:
                was = True
            if was != backend_now["fast_math"]:
                changed.append(f"backend.fast_math: {was!r} -> {backend_now['fast_math']!r} "
                               f"(set {backend.FAST_MATH_ENV}={int(was)} to resume as started"
                               + ("" if "fast_math" in started else
                                  "; this run predates the record, when fast math was on "
                                  "unless TCD_FAST_MATH=0 was set") + ")")
        if changed:
            raise ValueError(f"{out}: --resume with a scenario other than the one this run "
                             f"started with ({stored}): {io.shown_differences(changed)}. Resume "
                             "with that scenario and backend, or start a new run in another "
                             "--out directory")
        return
    out.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(stored) as tmp:
        pathlib.Path(tmp).write_text(scenario.text)
    # the scenario file it ran (tcd info's resume advice); its settings are in scenario.toml
    source = ({} if scenario.source.startswith("<")
              else {"scenario_file": str(pathlib.Path(scenario.source).resolve())})
    io.write_json(out / "run.json", {**backend_now, "tcd_version": __version__, **source,
                                     "seeds": list(scenario.seeds)})     # (--seeds)


def run_info(out) -> str:
    """A readable summary of the run directory `out` (what `tcd run` writes there): its
    scenario and backend, whether a tcd process writes into it now, and each sample's state:
    done (its main results), stopped at a checkpoint (stage, phase, step, simulated time, when
    written), or not started. Read from the run's own files: nothing is built or compiled."""
    import tomllib
    out = pathlib.Path(out)
    stored = out / "scenario.toml"
    if not stored.is_file():
        raise ValueError(f"{out}: not a tcd run directory (it has no scenario.toml; `tcd info` "
                         "reads a run directory or a tcd HDF5 file)")
    try:
        stored_text = stored.read_text(encoding="utf-8")
        doc = tomllib.loads(stored_text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{stored}: cannot be read ({exc})") from None
    stage_docs = [st for st in doc.get("stage", []) if isinstance(st, dict)]
    stages = [st.get("kind", "?") for st in stage_docs]
    given = text_settings(stored_text)      # tcd run --set ...
    seeds = [s for s in doc.get("seeds", [1]) if isinstance(s, int)]
    seeds += sorted(int(d.name[7:]) for d in out.glob("sample_*")
                    if d.is_dir() and d.name[7:].isdigit() and int(d.name[7:]) not in seeds)
    lines = [f"{out}: tcd run of scenario {doc.get('name', '?')!r} ({stored}): stages "
             f"{', '.join(stages) or '?'}; seeds {', '.join(map(str, seeds))}"]
    started = {}
    try:
        started = json.loads((out / "run.json").read_text())
        lines.append(f"backend: {started.get('arch', '?')} {started.get('precision', '?')}, "
                     f"tcd {started.get('tcd_version', '?')}")
    except (OSError, ValueError, AttributeError):
        lines.append("backend: unknown (run.json missing or unreadable)")
    scenario_file, file_note = _scenario_file(started, stored, stored_text)
    begun = started.get("seeds") if isinstance(started, dict) else None
    if file_note:
        lines.append(file_note)
    holder = _lock_holder(out / LOCK_FILE)
    if holder:
        lines.append(f"running now: a tcd process writes into it ({holder})")
    batch = out / "batch_checkpoint.h5"
    if batch.is_file() and (out / "summary.json").is_file() and not holder:
        # a finished batch keeps its last checkpoint (a longer shear goes on from it: --from)
        lines.append(f"batch: done (its last checkpoint: {batch.name})")
    elif batch.is_file():
        lines.append("batch: " + _checkpoint_line(batch, stages, batched=True, live=bool(holder)))
    for seed in seeds:
        d = out / f"sample_{seed}"
        summary, ck = d / "summary.json", d / "checkpoint.h5"
        if summary.is_file():
            text = _done_line(summary)
        elif ck.is_file():
            text = _checkpoint_line(ck, stages, live=bool(holder))
        elif batch.is_file() and d.is_dir():
            text = "in the batch (above)" + _shear_so_far(batch, seed)
        elif d.is_dir() and any(any(d.glob(pattern)) for pattern in STAGE_RESULTS):
            # (any(d.glob(...)): a generator is always true, so every started folder without a
            # checkpoint was said to be refused: session 72's review)
            text = ("its checkpoint.h5 is missing, yet it holds the results of a stage: "
                    "--resume refuses it (put the checkpoint back, or move the folder away "
                    "to run the sample again)")
        elif (d / "states.h5").is_file():
            text = "started, no checkpoint yet"
        elif isinstance(begun, list) and seed not in begun:
            text = f"not started (the run began with --seeds {','.join(map(str, begun))})"
        else:
            text = "not started"
        lines.append(f"sample_{seed}: {text}")
    if (out / "summary.json").is_file():
        lines.append(f"run summary: {out / 'summary.json'} (`tcd figures {shlex.quote(str(out))}` draws the "
                     "figures and Table 2)")
    else:
        # the options the run was started with that its scenario file does not say: the
        # backend and the seeds (left out, the command was refused or ran the seeds left out)
        words = []
        written = doc.get("backend") if isinstance(doc.get("backend"), dict) else {}
        for key, default in (("arch", "cpu"), ("precision", "f64")):
            value = started.get(key) if isinstance(started, dict) else None
            if isinstance(value, str) and value != written.get(key, default):
                words += [f"--{key}", value]
        scenario_seeds = doc.get("seeds", [1])
        if isinstance(begun, list) and begun and begun != scenario_seeds:
            words += ["--seeds", ",".join(map(str, begun))]
        options = (" " + shlex.join(words) if words else "") + (" " + given if given else "")
        lines.append("run summary: not written yet (the run has not finished; resume it with "
                     f"`tcd run {shlex.quote(scenario_file) if scenario_file else '<its scenario>'}"
                     f" --out {shlex.quote(str(out))}{options}"
                     f"{' --batch' if batch.is_file() else ''} --resume`)" if not holder else
                     "run summary: not written yet")
    return "\n".join(lines)


def _scenario_file(started, stored: pathlib.Path, text: str) -> tuple[str, str]:
    """(path, note) of the scenario file a run started from, as its run.json (`started`)
    recorded it (runs since session 58): the path when that file still holds the run's
    scenario (`text`, read from `stored`, with the run's `--set` settings), else ""; the note
    says which file and, where it cannot serve a --resume any more, why."""
    from .config import ScenarioError, load_scenario, parse_setting
    path = started.get("scenario_file") if isinstance(started, dict) else None
    if not isinstance(path, str) or not path:
        return "", ""
    try:
        words = shlex.split(text_settings(text))
        settings = [parse_setting(w) for w in words[1::2]]
        begun = started.get("seeds")
        begun = begun if isinstance(begun, list) and all(isinstance(s, int) for s in begun) else None
        changed = scenario_changes(text, load_scenario(path, settings, seeds=begun), str(stored))
    except ScenarioError as exc:
        return "", f"scenario file: {path}, which cannot serve a --resume now ({exc.problems[0][1]})"
    except (OSError, ValueError) as exc:
        return "", f"scenario file: {path}, which cannot be read back now ({exc})"
    if changed:
        return "", (f"scenario file: {path}, changed since the run started "
                    f"({io.shown_differences(changed)}): a --resume needs the run's scenario "
                    f"({stored}) back in a file")
    return path, f"scenario file: {path}"


def _lock_holder(path: pathlib.Path) -> str:
    """Who holds the run lock at `path` ("" when no process does, or it cannot be told)."""
    try:
        with open(path, encoding="utf-8") as f:
            return shared_lock(f)       # closing the file lets a lock taken go
    except OSError:
        return ""


def shared_lock(f) -> str:
    """Take a shared lock on the open run-lock file `f` without waiting: "" once it is held (or
    where locks cannot be taken), else who holds it exclusively, as that process wrote it
    there: a run that writes into the folder (run_lock)."""
    try:
        import fcntl
        fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return f.read().strip() or "a process that did not say which"
    except (ImportError, OSError):
        pass
    return ""


def _done_line(path: pathlib.Path) -> str:
    try:
        res = json.loads(path.read_text())
        if not isinstance(res, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as exc:
        return f"done, but {path} cannot be read ({exc})"
    parts = [f"done: {res['particles']} grains" if "particles" in res else "done"]
    if isinstance(res.get("tau_peak_MPa"), (int, float)):
        parts.append(f"peak {res['tau_peak_MPa']:.4g} MPa at {res.get('d_peak_mm', float('nan')):.3g} mm"
                     + (" (the end of the test: still rising, no failure)"
                        if res.get("peak_at_end") is True else ""))
    if isinstance(res.get("bonds_total"), int):
        parts.append(f"{res.get('bonds_broken', '?')} of {res['bonds_total']} bonds broken")
    if isinstance(res.get("packing_fraction"), (int, float)):
        parts.append(f"packing fraction {res['packing_fraction']:.3f}")
    wall = res.get("wall_time_s")
    if isinstance(wall, dict) and all(isinstance(v, (int, float)) for v in wall.values()):
        parts.append(f"{sum(wall.values()):.0f} s of wall time")
    return ", ".join(parts) + _branch_note(res)


def _branch_note(result) -> str:
    """The note `; went on from RUN at t = ... s (N setting(s) changed)` for a sample of a
    `tcd run --from` run (its result's `branched_from`, tcd.branch), else an empty string."""
    try:
        rec = result["branched_from"][-1]
        return f"; went on {io.branch_origin(rec)} ({len(rec['changes'])} setting(s) changed)"
    except (KeyError, IndexError, TypeError, ValueError):
        return ""


def _shear_so_far(path: pathlib.Path, seed: int | None = None) -> str:
    """'; the ring at D mm, S MPa, peak so far P MPa at Dp mm' from the series of the shear a
    checkpoint stopped in (a batch's: that of sample `seed`), its stress smoothed over its
    stage's window as the summary's peak; "" when it holds none, or stopped in another stage."""
    try:
        series, window, _ = io.checkpoint_shear_series(path, seed)
        d, tau = series["displacement"], series["shear_stress"]
        peak, at, _ = obs.peak_of(d, tau, float(window) * 1e-3)
        return (f"; the ring at {d[-1] * 1e3:.3f} mm, {tau[-1] / 1e6:.4g} MPa, peak so far "
                f"{peak / 1e6:.4g} MPa at {at * 1e3:.3g} mm")
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return ""


def _left_behind(sample_dir: pathlib.Path, meta: dict) -> str:
    """What a hard kill left in a stopped sample's folder that `--resume` clears: temporaries
    of interrupted writes, and frames written to states.h5 after the last checkpoint (whose
    `meta` records the frames it had)."""
    notes = []
    temporaries = io.stale_temporaries(sample_dir)
    if temporaries:
        notes.append(f"{len(temporaries)} temporary file(s) of an interrupted write "
                     f"({temporaries[0].name}{', ...' if len(temporaries) > 1 else ''})")
    try:
        recorded = meta.get("frames")
        states = sample_dir / "states.h5"
        extra = (io.frame_count(states) - int(recorded)
                 if isinstance(recorded, int) and states.is_file() else 0)
    except (OSError, ValueError):       # a states file that cannot be read: nothing said
        extra = 0
    if extra > 0:
        notes.append(f"{extra} frame(s) of states.h5 written after that checkpoint")
    return f"; left behind: {' and '.join(notes)} (--resume removes them)" if notes else ""


def _checkpoint_line(path: pathlib.Path, stages: list, *, batched: bool = False,
                     live: bool = False) -> str:
    """Where the checkpoint at `path` stands: "stopped in ...", or, while a process writes
    into the run (`live`), "running, its last checkpoint in ..."; a shear stage's line adds
    the ring's travel, the stress and the peak so far."""
    try:
        meta, _ = io.checkpoint_meta(path)
        if batched:
            phase = meta["phases"][0]       # one per sample, stepped together
            where = f"the shear of seeds {', '.join(map(str, meta['seeds']))}"
        else:
            k = int(meta["stage"])
            phase = meta.get("phase")
            where = (f"stage {k + 1} of {len(stages)} ({stages[k]})" if 0 <= k < len(stages)
                     else f"stage {k + 1}")
        text = f"{'running, its last checkpoint in' if live else 'stopped in'} {where}"
        if isinstance(phase, dict):
            layer = (phase.get("info") or {}).get("layer")
            name = repr(phase.get("name", "?")) + (f" of layer {layer + 1}"
                                                   if isinstance(layer, int) else "")
            number = (f"phase {meta['phase_index'] + 1} ({name})"
                      if isinstance(meta.get("phase_index"), int) else f"phase {name}")
            text += (f", {number} at step {meta.get('step_in_phase', '?')} of "
                     f"{'at most ' if phase.get('settle') else ''}{phase.get('steps', '?')}")
        elif isinstance(meta.get("phase_index"), int):     # between two phases
            text += f", before its phase {meta['phase_index'] + 1}"
        text += f", t = {float(meta['time']):.4f} s"
        if not batched:
            text += _shear_so_far(path)
        # the file's own time: its `created` attribute follows SOURCE_DATE_EPOCH when set (for
        # reproducible bytes), which made this line say "written 1970-01-01..."
        written = _dt.datetime.fromtimestamp(path.stat().st_mtime, _dt.timezone.utc)
        text += f"; checkpoint {path.name} written {written.isoformat(timespec='seconds')}"
        if batched:
            return text
        return (text + _branch_note(meta.get("result"))
                + ("" if live else _left_behind(path.parent, meta)))
    except KeyError as exc:     # a checkpoint file that is not a run's (a prepared sample)
        return (f"a checkpoint that cannot be read ({path}: its meta lacks {exc.args[0]!r}: "
                "not a run's checkpoint)")
    except (OSError, ValueError, TypeError, IndexError) as exc:
        reason = str(exc)
        return (f"a checkpoint that cannot be read ("
                f"{reason if reason.startswith(str(path)) else f'{path}: {reason}'})")


def batch_problem(scenario) -> str | None:
    """Why `scenario` cannot run as one batch (None when it can)."""
    stages = scenario.stages
    if len(stages) != 1 or stages[0].kind != "shear" or not getattr(stages[0], "sample", ""):
        return (f"{scenario.name}: --batch runs a scenario whose only stage is a shear of "
                "prepared samples (`sample = \"...\"`); this one has stages: "
                + ", ".join(st.kind for st in stages))
    if len(scenario.seeds) > MAX_SYSTEMS:
        return f"{scenario.name}: at most {MAX_SYSTEMS} samples in one batch, got {len(scenario.seeds)}"
    return None


def run_batch(scenario, out_dir, *, resume: bool = False, progress: bool = True) -> dict:
    """Shear every sample of `scenario` at once, as one batched simulation (Simulation.batch:
    the samples side by side in the same fields, one step for all; on the CPU the Gauss-Seidel
    runs one sample per core, on a GPU all in one set of launches).

    For scenarios whose only stage is a shear of prepared samples (`sample = ".../{seed}..."`):
    preparation phases end at different times per sample, so they are not batched. The outputs
    are those of `run_scenario` (sample_<seed>/ series, states, summary.json; summary.json),
    each sample's numbers computed from its own system; the checkpoint is one file for the
    batch (batch_checkpoint.h5). A batch has one clock: every sample starts its shear at the
    latest of the prepared samples' times (an unbatched run starts at the sample's own time:
    the series' `time` differs by the shift, the other numbers agree to rounding; bit for bit
    in session 48's audit). A batch stopped before its first checkpoint starts over on
    `--resume`."""
    from .simulation import Simulation, SystemView
    problem = batch_problem(scenario)
    if problem:
        raise ValueError(problem)
    stage = scenario.stages[0]
    seeds = list(scenario.seeds)
    out = pathlib.Path(out_dir)
    ck_path = out / "batch_checkpoint.h5"
    from_start = not resume
    if resume and ck_path.exists():     # the files it goes on from, whole
        for path in [ck_path] + [out / f"sample_{seed}" / "states.h5" for seed in seeds]:
            if path.is_file():
                check_whole(path, "start the batch again in a new --out directory")
    if resume and not ck_path.exists():
        if not _stopped_before_first_checkpoint(out):
            raise FileNotFoundError(f"{out}: nothing to resume (no batch_checkpoint.h5)")
        # a batch stopped while it was built: it starts over, as an unbatched run does
        # (run_scenario); its scenario is still checked against the one it started with
        print(f"tcd: note: {out}: no batch checkpoint yet (the batch stopped before its first): "
              "it starts from the beginning", file=sys.stderr)
        from_start = True
    if from_start:
        check_samples(scenario, seeds)
    backend.check_available(scenario.backend.arch)     # before anything is written
    with recorded_run(scenario, out, resume):
        backend.init(scenario.backend.arch, scenario.backend.precision)
        t_start = time.perf_counter()
        dirs = {seed: out / f"sample_{seed}" for seed in seeds}
        protos = {seed: PROTOCOLS["shear"](stage, scenario, seed) for seed in seeds}
        h = scenario.solver.time_step
        if not from_start:
            arrays, meta = io.load_checkpoint(ck_path)
            check_run_checkpoint(scenario, ck_path, meta, BATCH_CHECKPOINT_KEYS, seeds=seeds)
            batch = restore_checkpoint(scenario, ck_path, arrays, meta)
            for seed in seeds:
                restore_frames(dirs[seed] / "states.h5", (meta.get("frames") or {}).get(str(seed)),
                               ck_path, seed)
            phases = [Phase.from_json(ph) for ph in meta["phases"]]
            step_in_phase, next_snapshot = meta["step_in_phase"], meta["next_snapshot"]
            results = meta["results"]
            series = [_restored_series(arrays, f"series/{seed}/",
                                       (meta.get("series_keys") or {}).get(str(seed)))
                      for seed in seeds]
            wall_before = meta["wall_time_s"]
        else:
            for d in dirs.values():
                d.mkdir(parents=True, exist_ok=True)
                for stale in ("states.h5", "checkpoint.h5", "summary.json"):
                    (d / stale).unlink(missing_ok=True)
            paths = [stage.sample.format(seed=seed) for seed in seeds]
            sims, phases = plan_shears(scenario, stage, seeds, paths)
            batch = Simulation.batch(sims)
            for o in sims:
                o.close()
            step_in_phase, next_snapshot, wall_before = 0, 0.0, 0.0
            series = [{} for _ in seeds]
            results = [{"seed": seed, "stages": {}, "wall_time_s": {}, "batched_with": seeds,
                        "inputs": {"0:shear": io.file_record(path)}}
                       for seed, path in zip(seeds, paths)]
        for res in results:
            _record_loop_mode(res)
        views = SystemView.all(batch)
        if from_start:
            for seed, view, res in zip(seeds, views, results):
                k = io.append_frame(dirs[seed] / "states.h5", frame_of(view), time=batch.time,
                                    step=batch.step_index, stage="shear", scenario_text=scenario.text,
                                    tcd_version=__version__)
                res["stage_first_frame"] = {"0": k}
            next_snapshot = next_snapshot_after(batch.time, scenario.output.snapshot_every)
        t_loop = time.perf_counter() - wall_before
        last_ck = time.perf_counter()

        def checkpoint():
            arrays = dict(batch.state_dict())
            for seed, ser in zip(seeds, series):
                arrays.update({f"series/{seed}/{k}": np.asarray(v) for k, v in ser.items()})
            meta = {"seeds": seeds, "phases": [ph.to_json() for ph in phases],
                    "step_in_phase": step_in_phase, "next_snapshot": next_snapshot,
                    "results": results, **simulation_meta(batch),
                    "wall_time_s": time.perf_counter() - t_loop, "tcd_version": __version__,
                    "scenario_text": scenario.text,
                    "series_keys": {str(seed): list(ser) for seed, ser in zip(seeds, series)},
                    "frames": {str(seed): io.frame_count(dirs[seed] / "states.h5") for seed in seeds}}
            io.save_checkpoint(ck_path, arrays, meta)

        steps = phases[0].steps
        with DeferredInterrupt() as interrupt:
            bar = Progress(progress, f"batch of {len(seeds)} shear", steps, h)
            bar.update(step_in_phase, batch.time)
            while step_in_phase < steps:
                protos[seeds[0]].before_step(batch, phases[0])
                rec = batch.step()
                step_in_phase += 1
                if step_in_phase % scenario.output.series_every == 0 or step_in_phase == steps:
                    # each view's numbers as a run of its system alone records them; the views
                    # share one read of each field per step (SystemView.all: a read waits for a GPU)
                    for k, (seed, view) in enumerate(zip(seeds, views)):
                        sweeps, residual = view.solver_stats()
                        row = {"time": batch.time, "step": batch.step_index, "sweeps": sweeps,
                               "residual": residual, "contacts": view.contact_count(),
                               "kinetic_energy": view.kinetic_energy()}
                        row.update(protos[seed].record(view, phases[k]))
                        for key, v in row.items():
                            series[k].setdefault(key, []).append(v)
                if batch.time >= next_snapshot - 1e-12:
                    for seed, view in zip(seeds, views):
                        io.append_frame(dirs[seed] / "states.h5", frame_of(view), time=batch.time,
                                        step=batch.step_index, stage="shear",
                                        scenario_text=scenario.text, tcd_version=__version__)
                    next_snapshot = next_snapshot_after(batch.time, scenario.output.snapshot_every)
                bar.count_sweeps(rec.sweeps)
                if step_in_phase % 100 == 0 or bar.due():
                    bar.update(step_in_phase, batch.time, f"sweeps={rec.sweeps}")
                last_ck = _checkpoint_if_due(interrupt, last_ck, scenario.output.checkpoint_every_s,
                                             checkpoint, bar)
            bar.close()
            checkpoint()
        wall = time.perf_counter() - t_loop
        samples = []
        for k, (seed, view) in enumerate(zip(seeds, views)):
            res, arrays = results[k], {key: np.asarray(v) for key, v in series[k].items()}
            states = dirs[seed] / "states.h5"
            numbers, attrs = _shear_numbers(protos[seed], view, phases[k], arrays, states,
                                            res.get("stage_first_frame", {}).get("0"))
            _print_warnings(seed, numbers)
            numbers.update(solver_numbers(arrays, batch.settings.max_sweeps))
            numbers["wall_time_s"] = wall
            numbers["steps"] = int(step_in_phase)
            res["stages"]["0:shear"] = numbers
            res["wall_time_s"]["0:shear"] = wall
            res["phases"] = [{"stage": "shear", "phase": phases[k].name, "steps": step_in_phase,
                              "end_time": batch.time, **phases[k].info}]
            res["last_phase"] = phases[k].to_json()
            _write_series(dirs[seed], "shear", arrays, attrs)
            _append_last_frame(states, view, "shear", scenario.text)
            samples.append(_write_sample_summary(dirs[seed], seed, res))
        summary = summarize(scenario, samples)
        summary["wall_time_s"]["total_this_invocation"] = time.perf_counter() - t_start
        summary["batched"] = True
        io.write_json(out / "summary.json", summary)
        batch.close()
        return summary


# held by a worker while it runs a sample (_watch_parent waits for it)
_JOB_RUNNING = threading.Lock()


def _watch_parent(parent: int, stop=None) -> None:
    """A `--jobs` worker's initializer: when its parent is gone (SIGKILL, an out-of-memory
    kill), the worker finishes the sample it is running (its files, then its lock) and ends.
    It used to wait for its next sample for ever, holding its memory (session 47's audit: both
    workers of a killed `--jobs 2` run still asleep minutes after their samples were done).
    `stop`: the run's stop (an Event the parent sets). A worker told to stop ends once it is
    idle,
    so that a pool shut down after a worker died (its SIGTERM to the others) is not left
    waiting for ever on one that only noted it."""
    worker_signals.enter_worker()       # a Ctrl-C or SIGTERM between samples: none starts after
    worker_signals.stop_event = stop
    worker_signals.guard_report_streams()       # its terminal closed: its samples go on

    def watch():
        idle_since_stop = 0
        while os.getppid() == parent:
            time.sleep(0.5)
            if worker_signals.stopping() and not _JOB_RUNNING.locked():
                idle_since_stop += 1
                if idle_since_stop >= 2 and _JOB_RUNNING.acquire(blocking=False):
                    os._exit(0)     # idle for two looks (its last result sent): done
            else:
                idle_since_stop = 0
        with _JOB_RUNNING:
            os._exit(0)
    threading.Thread(target=watch, name="tcd-parent-watch", daemon=True).start()


def _sample_job(text, source, arch, precision, seed, sample_dir, resume, progress,
                cpu_threads=None) -> dict:
    """A sample in a `--jobs` worker; one that comes after the worker was told to stop
    (worker_signals.stop_requested: a SIGTERM or Ctrl-C during its previous sample, or between
    two) is not started (KeyboardInterrupt before anything is written)."""
    if worker_signals.stopping():
        raise KeyboardInterrupt(f"sample {seed} not started: the run was stopped")
    with _JOB_RUNNING:
        return _run_sample_job(text, source, arch, precision, seed, sample_dir, resume,
                               progress, cpu_threads)


def _run_sample_job(text, source, arch, precision, seed, sample_dir, resume, progress,
                    cpu_threads=None) -> dict:
    """One sample in a worker process (see run_scenario's `jobs`), on `cpu_threads` threads of
    Taichi's CPU pool unless TCD_CPU_THREADS or TCD_PARALLEL_LOOPS says otherwise."""
    from .config import parse_scenario
    scn = parse_scenario(text, source, seeds=[seed]).with_overrides(arch=arch,
                                                                    precision=precision)
    if os.environ.get(backend.THREADS_ENV) or os.environ.get(backend.LOOPS_ENV):
        cpu_threads = None
    backend.init(arch, precision, cpu_threads=cpu_threads)
    return run_sample(scn, seed, pathlib.Path(sample_dir), resume=resume, progress=progress)


class DeferredInterrupt(SignalScope):
    """Ctrl-C (SIGINT), SIGTERM (`kill PID`, or a batch scheduler's notice before it ends a
    job) or SIGHUP (the terminal or SSH session closed) during a run takes effect at the end of the current step: the step loop writes a
    checkpoint there and raises KeyboardInterrupt, so an interrupted run always resumes from
    where it was stopped (not from the last periodic checkpoint, or from nothing when none was
    written yet). A second signal stops at once. Installed as SignalScope says. In a `--jobs`
    worker the stop holds for the worker's later samples too (worker_signals), and one that
    came before the sample began stops it at its first step."""
    signals = worker_signals.STOP_SIGNALS

    def __init__(self):
        self._pending = False

    @property
    def pending(self) -> bool:
        """A stop is due: a signal came, or (in a `--jobs` worker) the run's parent stopped
        it (a signal to the parent alone, or one that came while this worker started)."""
        return self._pending or (worker_signals.in_worker and worker_signals.stopping())

    @pending.setter
    def pending(self, value: bool) -> None:
        self._pending = value

    def __enter__(self):
        super().__enter__()
        if worker_signals.stop_requested:
            self.pending = True         # came between _sample_job's check and this handler
        return self

    def _handler(self, signum, frame):
        if worker_signals.in_worker:            # the stop holds for its later samples
            worker_signals.stop_requested = True
        if self._pending:               # a second signal (the parent's stop is not one)
            raise KeyboardInterrupt
        self._pending = True


class ForwardTerm(SignalScope):
    """While samples run in worker processes (`--jobs N`), a SIGTERM or SIGHUP to the parent
    is passed on to the workers (as SIGTERM), each of which checkpoints at the end of its step and stops (their
    KeyboardInterrupt comes back through the futures), instead of killing the parent and
    leaving the workers running on their own. (Ctrl-C in a terminal reaches every process of
    the job already.) Installed as SignalScope says."""
    signals = worker_signals.END_SIGNALS

    def __init__(self, pool, stop=None):
        self.pool, self.stop = pool, stop

    def _handler(self, signum, frame):
        if self.stop is not None:
            self.stop.set()
        # ProcessPoolExecutor keeps its worker processes in _processes (pid -> Process; None
        # once it has shut down)
        for proc in list((getattr(self.pool, "_processes", None) or {}).values()):
            try:
                os.kill(proc.pid, signal.SIGTERM)
            except ProcessLookupError:          # that worker has just ended
                pass


def _finished_samples(out: pathlib.Path, exclude) -> list[dict]:
    """The summaries of the samples finished in the run directory `out` (its
    sample_<seed>/summary.json) but for the seeds in `exclude`: those that earlier invocations
    of a study split with --seeds ran into the same folder (a resume checks that they ran the
    same scenario)."""
    found = []
    for d in sorted(out.glob("sample_*")):
        seed = d.name[len("sample_"):]
        path = d / "summary.json"
        if seed.isdigit() and int(seed) not in exclude and path.is_file():
            try:
                res = json.loads(path.read_text())
            except (OSError, ValueError) as exc:
                raise ValueError(f"{path}: a finished sample's summary cannot be read ({exc}); "
                                 "the run's summary would leave it out") from None
            if isinstance(res, dict) and res.get("seed") == int(seed):
                found.append(res)
    return found


def stage_sizes(stage) -> str:
    """What a prepare stage will pour: its courses' sphere counts and mould, in words."""
    counts = [(course, stage.layer_particle_count(course)) for course in stage.courses]
    return (" + ".join(f"{n} {course}" for course, n in counts) + f" spheres "
            f"({sum(n for _, n in counts)} in all, sizes x {stage.size_scale:g}) in a "
            f"{stage.cylinder_diameter_mm:g} mm mould, layers of {stage.layer_height_mm:g} mm")


def next_snapshot_after(t: float, every: float) -> float:
    """The time of the next snapshot after one written at `t`: the next multiple of `every`
    (a run that starts from a sample at t > 0 writes no burst of frames to catch up, and a
    shear from a saved sample writes the frames of the same shear inside a full run)."""
    return (math.floor(t / every + 1e-9) + 1) * every


def _checkpoint_if_due(interrupt, last_ck: float, every_s: float, save, bar) -> float:
    """Checkpoint (`save()`) when `every_s` seconds of wall time have passed since `last_ck` or
    a Ctrl-C is pending; after a Ctrl-C, stop (KeyboardInterrupt) once the checkpoint is
    written. Returns the time of the latest checkpoint."""
    if interrupt.pending or time.perf_counter() - last_ck >= every_s:
        save()
        last_ck = time.perf_counter()
        if interrupt.pending:
            bar.close()
            raise KeyboardInterrupt
    return last_ck


def _record_loop_mode(result: dict) -> None:
    """Append this invocation's loop mode to a sample's `cpu_loops` (backend.loop_mode: with
    fast math on the numbers' last bits depend on it; a resumed run adds one entry per
    invocation)."""
    result["cpu_loops"] = list(result.get("cpu_loops", [])) + [backend.loop_mode()]


def run_sample(scn, seed: int, sample_dir: pathlib.Path, *, resume: bool, progress: bool) -> dict:
    # the sample's own lock: a worker of `--jobs` outlives its parent when only the parent is
    # killed, and would go on writing here while a resumed run wrote the same files
    with run_lock(sample_dir), DeferredInterrupt() as interrupt:
        return _run_sample(scn, seed, sample_dir, resume=resume, progress=progress,
                           interrupt=interrupt)


def _run_sample(scn, seed: int, sample_dir: pathlib.Path, *, resume: bool, progress: bool,
                interrupt: DeferredInterrupt) -> dict:
    sample_dir.mkdir(parents=True, exist_ok=True)
    ck_path = sample_dir / "checkpoint.h5"
    states = sample_dir / "states.h5"
    h = scn.solver.time_step
    sim = None
    stage_idx, phase_idx, step_in_phase = 0, 0, 0
    phase = None
    series: dict = {}
    result = {"seed": seed, "stages": {}, "wall_time_s": {}}
    next_snapshot = 0.0
    if resume:      # (under the sample's lock: no other process writes here)
        _note_removed(io.remove_stale_temporaries(sample_dir))
    if resume and ck_path.exists():
        arrays, meta = io.load_checkpoint(ck_path)
        check_run_checkpoint(scn, ck_path, meta, SAMPLE_CHECKPOINT_KEYS, seeds=[seed])
        if not isinstance(meta["stage"], int) or not 0 <= meta["stage"] <= len(scn.stages):
            raise ValueError(f"{ck_path}: its stage {meta['stage']!r} is not one of the "
                             f"scenario's {len(scn.stages)} stages")
        sim = restore_checkpoint(scn, ck_path, arrays, meta)
        restore_frames(states, meta.get("frames"), ck_path, seed)
        stage_idx, phase_idx, step_in_phase = meta["stage"], meta["phase_index"], meta["step_in_phase"]
        phase = Phase.from_json(meta["phase"]) if meta["phase"] else None
        series = _restored_series(arrays, "series/", meta.get("series_keys"))
        result = meta["result"]
        next_snapshot = meta["next_snapshot"]
    elif states.exists():
        for stale in (states, ck_path):
            stale.unlink(missing_ok=True)
    _record_loop_mode(result)
    last_ck = time.perf_counter()

    def checkpoint():
        arrays = dict(sim.state_dict())
        arrays.update({"series/" + k: np.asarray(v) for k, v in series.items()})
        meta = {"stage": stage_idx, "phase_index": phase_idx, "step_in_phase": step_in_phase,
                "phase": phase.to_json() if phase else None, **simulation_meta(sim),
                "result": result, "next_snapshot": next_snapshot, "tcd_version": __version__, "seed": seed, "scenario_text": scn.text,
                # the series' column order (the checkpoint's datasets come back by name)
                "series_keys": list(series),
                # a resume cuts states.h5 back to these frames (a hard kill may have left more)
                "frames": io.frame_count(states) if states.exists() else 0}
        io.save_checkpoint(ck_path, arrays, meta)

    def timed_checkpoint():
        result["wall_time_s"][f"{stage_idx}:{stage.kind}"] = time.perf_counter() - t_stage
        checkpoint()

    while stage_idx < len(scn.stages):
        stage = scn.stages[stage_idx]
        proto = PROTOCOLS[stage.kind](stage, scn, seed)
        if stage.kind == "shear" and getattr(stage, "sample", "") and sim is None:
            path = stage.sample.format(seed=seed)
            sim = load_prepared(scn, path)
            # which file, with what in it: kept through a resume (the checkpoint's result)
            result.setdefault("inputs", {})[f"{stage_idx}:shear"] = io.file_record(path)
        t_stage = time.perf_counter() - result["wall_time_s"].get(f"{stage_idx}:{stage.kind}", 0.0)
        while True:
            if phase is None:
                if stage.kind == "prepare" and phase_idx == 0 and progress:
                    # before the first course is generated (seconds to minutes for millions)
                    print(f"[tcd] seed {seed} prepare: {stage_sizes(stage)}", file=sys.stderr,
                          flush=True)
                phase, sim = proto.plan(phase_idx, sim, sim.time if sim is not None else 0.0)
                if phase is None:
                    break
                sim.set_walls(phase.walls)
                step_in_phase = 0
                if phase_idx == 0:          # every stage's first state is kept
                    k = io.append_frame(states, frame_of(sim), time=sim.time, step=sim.step_index,
                                        stage=stage.kind, scenario_text=scn.text, tcd_version=__version__)
                    result.setdefault("stage_first_frame", {})[str(stage_idx)] = k
                    # that frame counts as the snapshot due now: the next comes a whole
                    # interval later (it used to come at the stage's first step)
                    next_snapshot = max(next_snapshot,
                                        next_snapshot_after(sim.time, scn.output.snapshot_every))
            bar = Progress(progress, f"seed {seed} {stage.kind}:{phase.name}", phase.steps, h)
            bar.update(step_in_phase, sim.time)
            stop = False
            while step_in_phase < phase.steps:
                proto.before_step(sim, phase)
                rec = sim.step()
                step_in_phase += 1
                stop = (phase.settle and step_in_phase >= phase.min_steps
                        and step_in_phase % SETTLE_CHECK_EVERY == 0
                        and settled(sim, getattr(stage, "settle_speed", 0.005)))
                # every series_every-th step, and each phase's last (so that a series always
                # ends where its phase ended, whatever series_every)
                if (step_in_phase % scn.output.series_every == 0 or stop
                        or step_in_phase == phase.steps):
                    # the velocities read once (each read copies a whole field: 0.2 ms for
                    # 5857 grains), for the kinetic energy and the protocol's record
                    motion = (sim.velocities(), sim.angular_velocities())
                    row = {"time": sim.time, "step": sim.step_index, "sweeps": rec.sweeps,
                           "residual": rec.residual, "contacts": rec.contacts,
                           "kinetic_energy": obs.kinetic_energy_of(*motion, *sim.inverse_masses())}
                    row.update(proto.record(sim, phase, motion))
                    for k, v in row.items():
                        series.setdefault(k, []).append(v)
                if sim.time >= next_snapshot - 1e-12:
                    io.append_frame(states, frame_of(sim), time=sim.time, step=sim.step_index,
                                    stage=stage.kind, scenario_text=scn.text, tcd_version=__version__)
                    next_snapshot = next_snapshot_after(sim.time, scn.output.snapshot_every)
                bar.count_sweeps(rec.sweeps)
                if step_in_phase % 100 == 0 or bar.due():
                    bar.update(step_in_phase, sim.time, f"sweeps={rec.sweeps}")
                if stop:
                    break
                last_ck = _checkpoint_if_due(interrupt, last_ck, scn.output.checkpoint_every_s,
                                             timed_checkpoint, bar)
            bar.close()
            end = getattr(proto, "phase_end", None)
            result.setdefault("phases", []).append({"stage": stage.kind, "stage_index": stage_idx,
                                                    "phase": phase.name,
                                                    "steps": step_in_phase, "end_time": sim.time,
                                                    **({"settled": bool(stop)} if phase.settle else {}),
                                                    **{k: v for k, v in phase.info.items()},
                                                    **(end(sim, phase) if end else {})})
            result["last_phase"] = phase.to_json()
            phase_idx += 1
            phase = None
            result["wall_time_s"][f"{stage_idx}:{stage.kind}"] = time.perf_counter() - t_stage
            checkpoint()
        # stage done: series, summary, prepared sample
        arrays = {k: np.asarray(v) for k, v in series.items()}
        if stage.kind == "shear":
            numbers, attrs = _shear_numbers(proto, sim, Phase.from_json(result["last_phase"]), arrays,
                                            states, result.get("stage_first_frame", {}).get(str(stage_idx)))
        else:
            stage_phases = [rec for rec in result.get("phases", [])
                            if rec.get("stage_index", stage_idx) == stage_idx
                            and rec.get("stage") == stage.kind]
            numbers = proto.finish(sim, stage_phases)
            attrs = ({"phase_names": ", ".join(f"{k} {name}" for k, name in
                                               enumerate(PREPARE_PHASES))}
                     if stage.kind == "prepare" else {})
        _print_warnings(seed, numbers)
        numbers.update(solver_numbers(arrays, sim.settings.max_sweeps,
                                      result.get("sweep_caps", {}).get(str(stage_idx))))
        numbers["wall_time_s"] = time.perf_counter() - t_stage
        numbers["steps"] = int(sum(rec["steps"] for rec in result.get("phases", [])
                                   if rec.get("stage_index", stage_idx) == stage_idx
                                   and rec.get("stage") == stage.kind))
        result["stages"][f"{stage_idx}:{stage.kind}"] = numbers
        _write_series(sample_dir, stage.kind, arrays, attrs)
        if stage.kind == "prepare":
            # with the stage's phase records, so the file alone gives the courses as built
            io.save_checkpoint(sample_dir / "prepared.h5", sim.state_dict(),
                               {"walls": [w.to_dict() for w in sim.walls], "time": sim.time,
                                "domain": [list(map(float, sim.domain[0])), list(map(float, sim.domain[1]))],
                                "phases": stage_phases,
                                # which course each layer id is (a render names them)
                                "courses": list(stage.courses)})
        _append_last_frame(states, sim, stage.kind, scn.text)       # and its last
        series = {}
        stage_idx += 1
        phase_idx = 0
        checkpoint()
    flat = _write_sample_summary(sample_dir, seed, result)
    sim.close()
    return flat


SERIES_UNITS = {"time": "s", "displacement": "m", "shear_force": "N", "shear_stress": "Pa",
                "kinetic_energy": "J", "top_plate_force": "N", "top_plate_z": "m",
                "top_plate_shear_force": "N", "spin": "rad/s"}


def _print_warnings(seed: int, numbers: dict) -> None:
    """A finished stage's warnings (its numbers' "warnings"), one line each on stderr."""
    for text in numbers.get("warnings", []):
        print(f"tcd: warning: seed {seed}: {text}", file=sys.stderr)


def _append_last_frame(states: pathlib.Path, sim, stage: str, scenario_text: str) -> None:
    """A stage's last state, unless the snapshot of this very step ends the file already (a
    snapshot interval that ends with the stage wrote the same frame twice)."""
    if io.last_frame_clock(states) != (float(sim.time), int(sim.step_index), stage):
        io.append_frame(states, frame_of(sim), time=sim.time, step=sim.step_index, stage=stage,
                        scenario_text=scenario_text, tcd_version=__version__)


def _shear_numbers(proto, sim, phase, arrays: dict, states, first_frame) -> tuple[dict, dict]:
    """A finished shear stage's numbers (with how far the grains moved since the stage's first
    frame) and the attributes of its series file."""
    x_start = io.read_frame(states, first_frame)["particles/x"] if first_frame is not None else None
    numbers = proto.finish(sim, phase, arrays, x_start)
    attrs = {"tau_peak": numbers["tau_peak_MPa"] * 1e6, "tau_peak_units": "Pa",
             "d_peak": numbers["d_peak_mm"] * 1e-3, "d_peak_units": "m",
             "smoothing_window": proto.cfg.smoothing_window_mm * 1e-3,
             "smoothing_window_units": "m"}
    return numbers, attrs


def solver_numbers(arrays: dict, max_sweeps: int, caps=None) -> dict:
    """How well a stage's steps converged, from its series (every step's at series_every = 1,
    else those recorded): `recorded_steps`, `steps_at_sweep_cap` (the steps that stopped at
    max_sweeps, their residual above the tolerance) and `largest_residual`. `caps`: where a
    run went on from another under another cap (`tcd run --from`), [[first row, cap], ...]:
    each row is counted against the cap it ran under."""
    sweeps = np.asarray(arrays.get("sweeps", []), dtype=float)
    residual = np.asarray(arrays.get("residual", []), dtype=float)
    limit = np.full(len(sweeps), float(max_sweeps))
    for start, cap in sorted(caps or []):
        limit[int(start):] = float(cap)
    out = {"recorded_steps": int(len(sweeps)),
           "steps_at_sweep_cap": int(np.count_nonzero(sweeps >= limit))}
    if residual.size and np.any(np.isfinite(residual)):
        out["largest_residual"] = float(np.nanmax(residual))
    return out


def _write_series(sample_dir: pathlib.Path, kind: str, arrays: dict, attrs: dict) -> None:
    if arrays:
        io.write_series(sample_dir / f"{kind}_series.h5", arrays,
                        units={k: u for k, u in SERIES_UNITS.items() if k in arrays}, attrs=attrs,
                        csv_path=sample_dir / f"{kind}_series.csv")


def _write_sample_summary(sample_dir: pathlib.Path, seed: int, result: dict) -> dict:
    """sample_<seed>/summary.json: the run's record of the sample with each stage's headline
    numbers at the top level; returns it."""
    flat = {"seed": seed, **result}
    for key, numbers in result["stages"].items():
        if key.endswith("prepare"):
            flat.update({"particles": numbers["particles"], "packing_fraction": numbers["packing_fraction"]})
        if key.endswith("shear"):
            flat.update({k: numbers[k] for k in ("tau_peak_MPa", "d_peak_mm", "residual_MPa", "bonds_total",
                                                  "bonds_broken", "bonds_broken_tension", "bonds_broken_shear",
                                                  "particles")})
            if "peak_at_end" in numbers:    # since session 55: not in a stage finished before
                flat["peak_at_end"] = numbers["peak_at_end"]
    io.write_json(sample_dir / "summary.json", flat)
    return flat


def plan_shears(scn, stage, seeds, paths) -> tuple[list, list]:
    """The prepared samples at `paths`, each with its shear (stage `stage`, seed from `seeds`)
    planned and its walls set, all starting at the latest of the samples' clocks (so that they
    can be batched: a batch has one clock). Returns (simulations, phases)."""
    sims = [load_prepared(scn, path) for path in paths]
    t0 = max(o.time for o in sims)
    phases = []
    for k, (seed, o) in enumerate(zip(seeds, sims)):
        o.time = t0
        phase, sims[k] = PROTOCOLS["shear"](stage, scn, seed).plan(0, o, t0)
        sims[k].set_walls(phase.walls)
        phases.append(phase)
    return sims, phases


# what a run's checkpoint meta holds (a file without them is not one: a prepared sample, ...)
SAMPLE_CHECKPOINT_KEYS = ("stage", "phase_index", "step_in_phase", "phase", "result",
                          "next_snapshot", "time", "walls", "domain")
BATCH_CHECKPOINT_KEYS = ("seeds", "phases", "step_in_phase", "next_snapshot", "results",
                         "wall_time_s", "time", "walls", "domain")


def check_run_checkpoint(scn, ck_path, meta, keys, *, seeds) -> None:
    """Refuse, naming the file, a checkpoint that is not a run's (`keys` missing from its
    meta), that holds other seeds, or that a run of another scenario wrote (checkpoints
    written before session 42 do not record their scenario or seed)."""
    if not isinstance(meta, dict):
        raise ValueError(f"{ck_path}: its meta is not a JSON object: not a checkpoint of a run")
    missing = [k for k in keys if k not in meta]
    if missing:
        raise ValueError(f"{ck_path}: not a checkpoint of a tcd run (its meta lacks "
                         f"{', '.join(missing)}): put back the run's own checkpoint, or start "
                         "the run again in a new --out directory")
    held = meta["seeds"] if "seeds" in meta else [meta.get("seed", seeds[0])]
    if held != seeds:
        raise ValueError(f"{ck_path}: the checkpoint holds seeds {held}, the scenario {seeds}")
    if "scenario_text" in meta:
        changed = scenario_changes(str(meta["scenario_text"]), scn, str(ck_path))
        if changed:
            raise ValueError(f"{ck_path}: written by a run of another scenario: "
                             f"{io.shown_differences(changed)}")


def restore_checkpoint(scn, ck_path, arrays: dict, meta: dict):
    """`restore_simulation` of a run's checkpoint, its problems named with the file."""
    try:
        io.check_state(arrays, str(ck_path), wall_slots=io.meta_wall_slots(arrays, meta))
        return restore_simulation(scn, arrays, meta)
    except (KeyError, TypeError, ValueError) as exc:
        text = str(exc) if not isinstance(exc, KeyError) else f"lacks {exc.args[0]!r}"
        raise ValueError(text if text.startswith(str(ck_path)) else
                         f"{ck_path}: cannot restore its state: {text}") from None


# the columns every series row starts with, in their order (_run_sample, run_batch)
SERIES_FIRST = ("time", "step", "sweeps", "residual", "contacts", "kinetic_energy")


def _restored_series(arrays: dict, prefix: str, keys) -> dict:
    """The series a checkpoint holds under `prefix`, as lists, in the order they were recorded
    (`keys`, from the checkpoint's meta): HDF5 gives a group's datasets back by name, and a
    resumed run wrote its series CSV with its columns sorted by name (bonds_broken_shear first,
    time eighth; session 47's audit). A checkpoint without the record (before session 47) has
    the columns every row starts with first, the others by name."""
    found = {k[len(prefix):]: list(v) for k, v in arrays.items() if k.startswith(prefix)}
    if not isinstance(keys, list) or sorted(keys) != sorted(found):
        keys = ([k for k in SERIES_FIRST if k in found]
                + [k for k in found if k not in SERIES_FIRST])
    return {k: found[k] for k in keys}


def restore_frames(states: pathlib.Path, frames, ck_path, seed: int) -> None:
    """Cut `states` back to the `frames` it had when the checkpoint `ck_path` was written: a
    run killed after that checkpoint (SIGKILL, a power cut) may have written later frames,
    which the resumed run writes again. A states file with fewer frames lost some since:
    refused, as the shear's numbers read its frames. (`frames` None: a checkpoint written
    before session 42, which did not record it: the file is left as it is.)"""
    if frames is None:
        return
    have = io.frame_count(states) if states.exists() else 0
    if have < int(frames):
        raise ValueError(f"{states}: {have} frames, but the checkpoint {ck_path} was written "
                         f"after frame {int(frames)}: the states file lost frames since, and "
                         "a resumed run would not match; restore it, or start the run again "
                         "in a new --out directory")
    dropped = io.keep_frames(states, int(frames)) if have else 0
    if dropped:
        print(f"tcd: note: seed {seed}: {states}: {dropped} frame(s) written after the last "
              "checkpoint were dropped (the resumed run writes them again)", file=sys.stderr)


def simulation_meta(sim) -> dict:
    """What `restore_simulation` reads of a file's meta besides its arrays: `sim`'s clock, step
    count, walls, bond law and broad-phase box (a run's checkpoints, one sample's or a batch's,
    hold it)."""
    return {"time": sim.time, "step": sim.step_index, "walls": [w.to_dict() for w in sim.walls],
            "bond_law": sim.bond_law.__dict__,
            "domain": [list(map(float, sim.domain[0])), list(map(float, sim.domain[1]))]}


def restore_simulation(scn, arrays: dict, meta: dict):
    from .simulation import BondLaw, Simulation
    from .walls import Wall
    sim = Simulation(arrays["particles/radius"], arrays["particles/x"], layer=arrays["particles/layer"],
                     walls=[Wall.from_dict(w) for w in meta["walls"]], density=scn.material.density,
                     friction=scn.material.friction, settings=scn.solver.to_settings(),
                     bond_law=BondLaw(**meta.get("bond_law", {})) if meta.get("bond_law") else scn.bond.to_law(),
                     domain=tuple(np.asarray(d) for d in meta["domain"]), time=meta["time"],
                     system=arrays.get("particles/system"))
    sim.load_state_dict(arrays)
    sim.step_index = int(meta.get("step", 0))
    return sim


#: largest |time| (s) of a prepared sample's clock: at 1e8 s (three years) a float still resolves
#: the smallest time step, 1e-7 s (its spacing there is 1.5e-8 s)
MAX_SAMPLE_TIME = 1e8


def read_prepared(path) -> tuple[dict, dict]:
    """The arrays and meta of the prepared sample at `path`, checked for everything a shear
    needs from it, without building a simulation (so that `tcd run` can check every seed's
    sample before the first one starts). Each problem is a ValueError naming the file."""
    from .simulation import MAX_WALLS, STATE_KEYS, check_state_arrays
    from .walls import Wall
    p = pathlib.Path(path)
    # the whole file first: a damaged one is a ValueError naming it (h5py's RuntimeError
    # was a traceback, the checksum's OSError an I/O error: session 71)
    io.check_readable(p)
    arrays, meta = io.load_checkpoint(p)
    if not isinstance(meta, dict):
        raise ValueError(f"{p}: its 'meta' attribute is not a JSON object")
    if "phase_index" in meta:
        raise ValueError(f"{p}: a run checkpoint (stage {meta.get('stage')}, phase "
                         f"{meta.get('phase_index')}), not a prepared sample: give the run's "
                         "sample_<seed>/prepared.h5, or continue that run with --resume")
    missing = [k for k in STATE_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"{p}: not a prepared sample: it lacks {', '.join(missing)}")
    if len(arrays["bonds/state"]):
        raise ValueError(f"{p}: the sample has {len(arrays['bonds/state'])} bonds: it was "
                         "sheared already; a shear stage starts from an unbonded prepared sample")
    # the schema's checks (shapes, dtypes, indices, radii, positions), as for every state read;
    # contacts may touch any wall slot: the shear replaces the sample's walls with its own
    io.check_state(arrays, str(p), wall_slots=MAX_WALLS)
    if len(arrays["particles/x"]) == 0:
        raise ValueError(f"{p}: particles/x holds no particles")
    try:        # a simulation's checks (inverse masses, loads, velocities, contacts, bonds)
        check_state_arrays(arrays)
    except ValueError as exc:
        raise ValueError(f"{p}: {exc}") from None
    try:
        walls = meta["walls"]
        if not isinstance(walls, list):
            raise TypeError("not a list")
        for w in walls:
            Wall.from_dict(w)
        domain = np.asarray(meta["domain"], dtype=float)
        if domain.shape != (2, 3) or not np.all(np.isfinite(domain)):
            raise ValueError(f"domain must be two finite 3-vectors, got {meta['domain']!r}")
        if not abs(float(meta["time"])) < MAX_SAMPLE_TIME:
            raise ValueError(f"time must be finite and within +-{MAX_SAMPLE_TIME:g} s (the "
                             f"clock must still advance by a time step), got {meta['time']!r}")
    except KeyError as exc:
        raise ValueError(f"{p}: its meta lacks {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{p}: bad meta: {exc}") from None
    return arrays, meta


def check_samples(scn, seeds) -> None:
    """Read and check, for each of `seeds`, the prepared sample of every shear stage that
    starts from a file: a bad sample of the fifth seed is reported before the first starts."""
    from .walls import Wall
    for stage in scn.stages:
        if stage.kind == "shear" and getattr(stage, "sample", ""):
            for seed in seeds:
                path = stage.sample.format(seed=seed)
                arrays, meta = read_prepared(path)
                # what the shear's plan needs of the sample: its mould, top plate and height
                proto = PROTOCOLS["shear"](stage, scn, seed)
                *_, problems = proto.sample_geometry(
                    [Wall.from_dict(w) for w in meta["walls"]], np.asarray(arrays["particles/x"]),
                    np.asarray(arrays["particles/radius"]), float(meta["time"]))
                problems += mass_problems(arrays, scn.material.density)
                if problems:
                    raise ValueError(f"{path} (seed {seed}): {'; '.join(problems)}")


#: how far (relative) a prepared grain's mass may be from density * 4/3 pi r^3, and its moment
#: of inertia from 2/5 m r^2: the rounding of an f32 state, with a margin
MASS_TOLERANCE = 1e-5


def mass_problems(arrays: dict, density: float) -> list[str]:
    """What is wrong with a prepared sample's masses for a shear whose scenario says
    `density`: the shear runs with the sample's own masses (particles/inv_mass, inv_inertia),
    so masses of another density, or not those of solid spheres, would go unnoticed in its
    results. A kinematic grain (both inverses 0) is allowed."""
    r = np.asarray(arrays["particles/radius"], dtype=float)
    inv_m = np.asarray(arrays["particles/inv_mass"], dtype=float)
    inv_i = np.asarray(arrays["particles/inv_inertia"], dtype=float)
    free = inv_m > 0
    problems = []
    if np.any(~free & (inv_i != 0)):
        problems.append(f"{int(np.count_nonzero(~free & (inv_i != 0)))} grain(s) have no inverse "
                        "mass (kinematic) but a nonzero inverse moment of inertia")
    if not np.any(free):
        return problems
    rf, mf = r[free], 1.0 / inv_m[free]
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        rho = mf / (4.0 / 3.0 * np.pi * rf**3)
        inertia = 1.0 / inv_i[free]
        off = np.abs(inertia / (0.4 * mf * rf**2) - 1.0)
    lo, hi = float(np.min(rho)), float(np.max(rho))
    if not (abs(lo / density - 1.0) <= MASS_TOLERANCE and abs(hi / density - 1.0) <= MASS_TOLERANCE):
        held = f"{lo:.6g} kg/m^3" if hi <= lo * (1 + MASS_TOLERANCE) else f"{lo:.6g} to {hi:.6g} kg/m^3"
        problems.append(f"its grains' masses (particles/inv_mass and radius) are those of a density "
                        f"of {held}, and the scenario's [material] density is {density:g}: the shear "
                        "would run with the sample's masses; set density to the sample's, or "
                        "prepare the sample with this density")
    bad = ~(off <= MASS_TOLERANCE)
    if np.any(bad):
        problems.append(f"{int(np.count_nonzero(bad))} grain(s) have a moment of inertia "
                        "(particles/inv_inertia) other than a solid sphere's 2/5 m r^2")
    return problems


def load_prepared(scn, path):
    """The prepared sample at `path` (a run's sample_<seed>/prepared.h5, or a file of that
    format) as a simulation. A run's checkpoint.h5, or a sample that already has bonds (it
    was sheared), is refused: shearing it would shear a sample twice, or half-prepared."""
    arrays, meta = read_prepared(path)
    problems = mass_problems(arrays, scn.material.density)
    if problems:
        raise ValueError(f"{path}: {'; '.join(problems)}")
    try:
        return restore_simulation(scn, arrays, meta)
    except ValueError as exc:       # the sample cannot be simulated: say which file it is
        message = str(exc)
        raise ValueError(message if message.startswith(str(path)) else f"{path}: {message}") \
            from None


def paper_test_differences(scn, samples: list) -> list[str]:
    """How the run's shear test differs from the paper's Leutner test (its stage's speed and
    displacement, its samples' moulds and heights): `tcd.observables.paper_test_differences`.
    A scenario without a shear stage has no test to compare."""
    shears = [st for st in scn.stages if st.kind == "shear"]
    if not shears:
        return ["no shear test"]
    numbers = [next((v for k, v in (s.get("stages") or {}).items() if k.endswith("shear")), s)
               for s in samples]        # each sample's shear stage (a sample of its own: itself)
    return obs.paper_test_differences(shears[0].velocity_mm_per_min, shears[0].displacement_mm,
                                      [n.get("mould_diameter_mm") for n in numbers],
                                      [n.get("sample_height_mm") for n in numbers])


def summarize(scn, samples: list) -> dict:
    """The run's summary: its samples, their mean and population std, and, when its test is
    the paper's Leutner test (`paper_test`), the relative error of the mean to Table 2's
    experiments; another test (`paper_test_differences` says how it differs) is not compared
    with them (`experiment`, `paper_simulation` and `relative_error` are null)."""
    differences = paper_test_differences(scn, samples)
    mean, std, rel = obs.study_statistics(samples, PAPER_EXPERIMENT)
    wall = {f"sample_{s['seed']}": s.get("wall_time_s", {}) for s in samples}
    paper = not differences
    return {"scenario": scn.name, "tcd_version": __version__, "arch": scn.backend.arch,
            "precision": scn.backend.precision, "samples": samples, "mean": mean, "std": std,
            "paper_test": paper, "paper_test_differences": differences,
            "experiment": PAPER_EXPERIMENT if paper else None,
            "paper_simulation": PAPER_SIMULATION if paper else None,
            "relative_error": rel if paper else None, "wall_time_s": wall}
