"""`tcd run NEW.toml --from RUN`: a new run that goes on from where another run's samples
stand (their checkpoints), under other solver or output settings, or with a longer shear.

What it is for: a convergence check from one state (the same test continued at another time
step or tolerance, as LMGC90 users restart from a saved state with a new command file), and a
shear test taken further than it was planned (`displacement_mm` larger) without running it
again from the start.

What may differ between RUN's scenario and NEW's (anything else is refused, naming it):
    name, description and seeds (each seed of NEW must be one of RUN's samples),
    [solver] and [output] (every key; under another `time_step` what is left of the step
    budget of the phase under way is rescaled, so that the phase ends at the same simulated
    time; the steps it took stay counted as taken; the warm start's impulses, forces times
    the time step, are rescaled with it, so that the first step starts from the same forces),
    the stage under way: its `tolerance`, `max_sweeps` and `smoothing_window_mm`, and a shear
    stage's `displacement_mm` (not below where the test stands; a finished run whose last
    stage is a shear is reopened when it is larger),
    the stages not started yet, wholly; a started shear's `sample` path (the sample was read
    already: a scenario file moved elsewhere writes its relative path anew).
[material] and [bond] define the grains and bonds the state holds: to shear a prepared sample
with another bond law, start a shear run from its `prepared.h5` (`sample = ...`).

The backend (`--arch`, `--precision`) may differ too; a change of it is recorded with the others.
RUN is only read, under a shared hold of its locks: not while a run writes there (refused,
naming the process), and no run starts there while the files are copied. The new run's
folder gets RUN's files of each sample (states, series of finished stages, prepared sample)
and a checkpoint rewritten for NEW's scenario, which records where it came from
(`branched_from` in the sample's summary.json): its series and snapshots hold the whole
history, RUN's part first. Then it is resumed like an interrupted run of NEW
(`runner.run_scenario(..., resume=True)`), and a later interruption resumes with `--resume`.
"""
from __future__ import annotations

import contextlib
import json
import pathlib
import re
import shutil

import numpy as np

from . import io
from .export import TIME_STEPS_ATTR, frame_time_steps
from .protocols import Phase
from .runner import LOCK_FILE, shared_lock

#: what may change in the stage under way, by its kind
STAGE_UNDER_WAY = {"shear": ("tolerance", "max_sweeps", "smoothing_window_mm", "displacement_mm"),
                   "prepare": ()}
#: a checkpoint's arrays that are impulses over one step (N s: forces times the time step),
#: rescaled when the new run steps at another time step
IMPULSE_KEYS = tuple(key for key, unit in io.STATE_UNITS.items() if unit == "N s")
_STAGE_KEY = re.compile(r"^stage\[(\d+)\]\.([A-Za-z_]+)")


class BranchError(ValueError):
    """A branch that cannot be made: the message names the run, the sample and the reason."""


def _key(line: str) -> str:
    """The key of one `io.differences` line ("solver.time_step: 0.0002 -> 0.0001")."""
    return line.split(": ", 1)[0]


def _refused(changes: list, stage_idx: int, started: bool, stages) -> list:
    """The lines of `changes` that a branch from stage `stage_idx` (0-based; `started`: some
    of it has run) may not make."""
    bad = []
    for line in changes:
        key = _key(line)
        if key in ("name",) or key.startswith(("solver.", "output.")):
            continue
        m = _STAGE_KEY.match(key)
        if m:
            k = int(m.group(1)) - 1                 # differences number the stages from 1
            if k > stage_idx or (k == stage_idx and not started):
                continue                            # not started: wholly NEW's
            if (k == stage_idx and k < len(stages)
                    and m.group(2) in STAGE_UNDER_WAY.get(stages[k].kind, ())):
                continue
            if m.group(2) == "sample":      # read already: the state goes on from RUN's
                continue
        bad.append(line)
    return bad


def _shear_end(stage, t0: float) -> float:
    """The simulated time at which a shear stage that started at `t0` has moved its ring by
    its `displacement_mm`."""
    return t0 + stage.displacement_mm * 1e-3 / (stage.velocity_mm_per_min * 1e-3 / 60.0)


def _series_of(path: pathlib.Path) -> tuple[dict, list]:
    """A finished stage's series file as checkpoint arrays ("series/<key>") and its column
    order: the CSV's header, else the order a resumed run restores (runner._restored_series)."""
    from .runner import _restored_series
    header = None
    csv = path.with_suffix(".csv")
    if csv.is_file():
        with open(csv, encoding="utf-8") as fh:
            header = [c.split(" [", 1)[0] for c in fh.readline().strip().split(",")]
    found = {"series/" + k: v for k, v in io.read_series(path).items()}
    series = _restored_series(found, "series/", header)
    return {"series/" + k: found["series/" + k] for k in series}, list(series)


def plan_branch(scenario, source, out) -> dict:
    """Check that `scenario` can go on from run `source` into `out` and work out, per seed,
    the checkpoint it starts from; nothing is written. Returns {seed: (arrays, meta, files)}."""
    from .config import ScenarioError, parse_scenario
    from .runner import RESUMED_FILES, SAMPLE_CHECKPOINT_KEYS, _scenario_record
    source, out = pathlib.Path(source), pathlib.Path(out)
    if not source.is_dir():
        raise BranchError(f"--from {source}: not a run directory")
    if (source / "batch_checkpoint.h5").exists():
        raise BranchError(f"--from {source}: a batched run (--batch) keeps one checkpoint for "
                          "all its samples; --from goes on from a run of one sample per process")
    if out.resolve() == source.resolve() or source.resolve() in out.resolve().parents:
        raise BranchError(f"--out {out}: must be a new directory outside the run it goes on "
                          f"from ({source})")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise BranchError(f"--out {out}: exists and is not empty; --from writes a new run")
    plans = {}
    backend_changes = []        # RUN's backend (run.json) against this run's
    try:
        started = json.loads((source / "run.json").read_text())
        for key in ("arch", "precision"):
            was, now = started.get(key), getattr(scenario.backend, key)
            if was is not None and was != now:
                backend_changes.append(f"backend.{key}: {was!r} -> {now!r}")
    except (OSError, ValueError, AttributeError):
        pass
    written = parse_scenario(scenario.text, scenario.source, resolve_samples=False)
    for seed in scenario.seeds:
        sample = source / f"sample_{seed}"
        ck = sample / "checkpoint.h5"
        if not ck.is_file():
            raise BranchError(f"--from {source}: no checkpoint of seed {seed} ({ck}): the run "
                              "has no such sample, or it stopped before its first checkpoint")
        # every file of the sample it goes on from, whole (a damaged checkpoint was a
        # traceback; a damaged states.h5 or prepared.h5 was copied, then refused as the new
        # run's own: session 71)
        for path in sorted({p for pattern in RESUMED_FILES for p in sample.glob(pattern)}):
            if path.is_file():
                try:
                    io.check_readable(path)
                except ValueError as exc:
                    raise BranchError(f"--from {source}: {exc}: a run cannot go on from it; "
                                      "restore it from a copy") from None
        arrays, meta = io.load_checkpoint(ck)
        missing = [k for k in SAMPLE_CHECKPOINT_KEYS + ("scenario_text",) if k not in meta]
        if missing:
            raise BranchError(f"{ck}: not a checkpoint of a tcd run, or of one too old to "
                              f"branch from (its meta lacks {', '.join(missing)})")
        if meta.get("seed", seed) != seed:
            raise BranchError(f"{ck}: holds seed {meta.get('seed')}, not {seed}")
        try:        # `sample` paths as written: RUN's scenario file may have lain elsewhere
            old = parse_scenario(str(meta["scenario_text"]), scenario.source,
                                 resolve_samples=False)
        except ScenarioError as exc:
            reasons = "; ".join(f"{k}: {r}" if k else r for k, r in exc.problems)
            raise BranchError(f"{ck}: the scenario of that run cannot be read back ({reasons})") \
                from None
        changes = io.differences(_scenario_record(old), _scenario_record(written), base=1)
        if len(old.stages) != len(scenario.stages):
            raise BranchError(f"{ck}: that run has {len(old.stages)} stage(s), the scenario "
                              f"{len(scenario.stages)}: --from keeps the stages")
        stage_idx, phase_idx = int(meta["stage"]), int(meta["phase_index"])
        phase = Phase.from_json(meta["phase"]) if meta["phase"] else None
        sip = int(meta["step_in_phase"])
        result = meta["result"]
        t, h_old, h_new = float(meta["time"]), old.solver.time_step, scenario.solver.time_step
        files = [p for p in sorted(sample.iterdir()) if p.is_file() and p.name not in
                 ("checkpoint.h5", "summary.json", ".tcd.lock") and ".tmp" not in p.name]
        reopen = stage_idx == len(scenario.stages)
        if reopen:              # finished: only a longer shear of its last stage goes on
            last, was = scenario.stages[-1], old.stages[-1]
            if not (last.kind == "shear" and was.kind == "shear"
                    and last.displacement_mm > was.displacement_mm and result.get("last_phase")):
                raise BranchError(
                    f"{ck}: that run finished (t = {t:g} s); there is nothing left to run. A "
                    "finished shear goes on with a larger displacement_mm of its last stage")
            stage_idx = len(scenario.stages) - 1
            phase_idx, phase = 0, Phase.from_json(result["last_phase"])
            sip = phase.steps
        started = phase is not None or phase_idx > 0
        refused = _refused(changes, stage_idx, started, scenario.stages)
        if refused:
            where = (f"stage {stage_idx + 1} ({scenario.stages[stage_idx].kind})"
                     if stage_idx < len(scenario.stages) else "the end")
            raise BranchError(
                f"{ck}: --from goes on with other [solver] or [output] settings, the stage under "
                f"way's tolerance, max_sweeps, smoothing_window_mm or shear displacement_mm, and "
                f"stages not started yet; this run stands in {where}, and the scenario changes "
                f"{io.shown_differences(refused)}. Start a new run for that (a shear can start "
                "from a prepared sample: `sample = ...`)")
        if phase is not None:
            stage = scenario.stages[stage_idx]
            # the steps taken stay counted as taken; what is left of the phase's budget (and
            # of a settling phase's least steps) is rescaled to end at the same time
            same_h = h_new == h_old
            ratio = h_old / h_new
            if stage.kind == "shear" and phase.name == "shear":
                was = old.stages[stage_idx]
                if same_h and stage.displacement_mm == was.displacement_mm:
                    remaining = phase.steps - sip
                else:
                    remaining = int(round((_shear_end(stage, float(phase.info["t0"])) - t) / h_new))
                if remaining < 0:
                    moved = (t - float(phase.info["t0"])) * stage.velocity_mm_per_min / 60.0
                    raise BranchError(f"{ck}: its shear has moved the ring {moved:.4g} mm, past "
                                      f"the displacement_mm {stage.displacement_mm:g} asked")
            else:
                remaining = phase.steps - sip if same_h else int(round((phase.steps - sip) * ratio))
            phase.steps = sip + remaining
            if not same_h and phase.min_steps > sip:
                phase.min_steps = sip + int(round((phase.min_steps - sip) * ratio))
        record = {"run": str(source.resolve()), "time": t, "step": int(meta["step"]),
                  "stage": stage_idx + 1, "phase": phase.name if phase else None,
                  "changes": backend_changes + changes}
        if phase is not None and phase.name == "shear" and "t0" in phase.info:
            # how far the ring had moved (mm): where the curves of the two runs part
            record["displacement_mm"] = ((t - float(phase.info["t0"]))
                                         * old.stages[stage_idx].velocity_mm_per_min / 60.0)
        if h_new != h_old:
            # a step's impulses are its forces times H: the warm start of the first step at
            # the new H is the same forces (as the old impulses, it started the solver 2x
            # off for H / 2 and broke bonds: session 72's review)
            arrays = dict(arrays)
            for key in IMPULSE_KEYS:
                if key in arrays:
                    arrays[key] = np.asarray(arrays[key]) * (h_new / h_old)
        new_meta = dict(meta)
        new_meta.update({"scenario_text": scenario.text, "stage": stage_idx,
                         "phase_index": phase_idx, "step_in_phase": sip,
                         "phase": phase.to_json() if phase else None})
        new_result = dict(result)
        new_result["branched_from"] = list(result.get("branched_from", [])) + [record]
        if reopen:
            key = f"{stage_idx}:{scenario.stages[stage_idx].kind}"
            new_result["stages"] = {k: v for k, v in result["stages"].items() if k != key}
            phases = list(result.get("phases", []))
            for k in range(len(phases) - 1, -1, -1):
                if phases[k].get("stage_index") == stage_idx:
                    del phases[k]
                    break
            new_result["phases"] = phases
            series_file = sample / f"{scenario.stages[stage_idx].kind}_series.h5"
            if not series_file.is_file():
                raise BranchError(f"{series_file}: missing; the finished stage's series is "
                                  "needed to go on with it")
            arrays = {k: v for k, v in arrays.items() if not k.startswith("series/")}
            series, keys = _series_of(series_file)
            arrays.update(series)
            new_meta["series_keys"] = keys
            files = [p for p in files if p != series_file and p != series_file.with_suffix(".csv")]
        if phase is not None:
            # the stage's steps ran under the sweep cap of their run: recorded, so that its
            # `steps_at_sweep_cap` counts each against its own (it counted them all against
            # the new one: session 72's review)
            def cap(scn):
                own = getattr(scn.stages[stage_idx], "max_sweeps", None)
                return int(own if own is not None else scn.solver.max_sweeps)
            if cap(old) != cap(scenario):
                rows = len(np.asarray(arrays.get("series/sweeps", [])))
                caps = dict(new_result.get("sweep_caps", {}))
                caps[str(stage_idx)] = list(caps.get(str(stage_idx), [[0, cap(old)]])) + [
                    [rows, cap(scenario)]]
                new_result["sweep_caps"] = caps
        if old.output.snapshot_every != scenario.output.snapshot_every and "next_snapshot" in meta:
            # the next snapshot on the new schedule (it came at the old one's due time first:
            # a branch at 0.76 s to snapshots every 0.01 s wrote none before 0.80 s)
            from .runner import next_snapshot_after
            new_meta["next_snapshot"] = next_snapshot_after(t, scenario.output.snapshot_every)
        new_meta["result"] = new_result
        plans[seed] = (arrays, new_meta, files)
    return plans


def branch_run(scenario, source, out) -> str:
    """Write the new run's folder `out` for `scenario` from run `source` (see the module
    docstring): its records, and per seed RUN's files and the rewritten checkpoint. Every
    check comes first (plan_branch), so a refused branch writes nothing. Returns one line per
    seed saying where it goes on from."""
    from .runner import record_scenario
    out, source = pathlib.Path(out), pathlib.Path(source)
    with contextlib.ExitStack() as held:        # not while a run writes there
        for path in [source] + [source / f"sample_{seed}" for seed in scenario.seeds]:
            _read_lock(held, path / LOCK_FILE)
        plans = plan_branch(scenario, source, out)
        created = not out.exists()
        try:
            _write_branch(scenario, source, out, plans)
            record_scenario(scenario, out, resume=False)
        except BaseException:
            if created:         # a failed copy (a full disk, Ctrl-C) leaves no half a run
                shutil.rmtree(out, ignore_errors=True)
            raise
    lines = []
    for seed, (_, meta, _) in plans.items():
        rec = meta["result"]["branched_from"][-1]
        lines.append(f"seed {seed}: {io.branch_origin(rec, step=True)}, "
                     f"{len(rec['changes'])} setting(s) changed")
    return "\n".join(lines)


def _read_lock(held: contextlib.ExitStack, path: pathlib.Path) -> None:
    """A shared lock on a run's lock file `path` (runner.run_lock), held by `held`: a run that
    writes there holds it exclusively, so this refuses, naming it; while held, no run starts
    there. A missing lock file (no run ever wrote there, or no such folder) is left missing:
    the source is only read."""
    try:
        f = held.enter_context(open(path, encoding="utf-8"))
    except OSError:
        return
    holder = shared_lock(f)
    if holder:
        raise BranchError(f"--from {path.parent}: a tcd run writes into it now ({holder}); "
                          "go on from it once it has stopped or finished")


def _write_branch(scenario, source: pathlib.Path, out: pathlib.Path, plans: dict) -> None:
    """Each sample's folder of the new run: RUN's files, then the rewritten checkpoint."""
    for seed, (arrays, meta, files) in plans.items():
        dst = out / f"sample_{seed}"
        dst.mkdir(parents=True, exist_ok=True)
        for path in files:
            with io.atomic_path(dst / path.name) as tmp:
                shutil.copyfile(path, tmp)
        states = dst / "states.h5"
        if states.is_file():        # its scenario: the one its frames go on under
            with io.atomic_path(states) as tmp:
                with io.hdf5_writer(tmp, source=states, size=states.stat().st_size) as f:
                    segments = _time_steps_after(f, meta, scenario.solver.time_step)
                    f.attrs["scenario"] = scenario.text
                    f.attrs["branched_from"] = str(source.resolve())
                    if segments is not None:
                        f.attrs[TIME_STEPS_ATTR] = json.dumps(segments)
        io.save_checkpoint(dst / "checkpoint.h5", arrays, meta)


def _time_steps_after(f, meta: dict, h_new: float) -> list | None:
    """The `time_steps` record (export.TIME_STEPS_ATTR) of the open states file `f` once the
    new run's frames, from the checkpoint's (`meta["frames"]`) on, are stepped at `h_new`: the
    time step of each earlier frame as it was, then `h_new`; None when every frame is and
    will be at one time step (the scenario's then tells it)."""
    count = len(io._frame_names(f, f.filename))
    kept = meta.get("frames")
    kept = count if not isinstance(kept, int) else min(int(kept), count)
    steps = frame_time_steps(f, kept)
    segments = []
    for k, h in enumerate(steps + [float(h_new)]):
        if h is None:
            return None         # a frame of unknown time step: nothing to record
        if not segments or segments[-1][1] != h:
            segments.append([k, h])
    return segments if len(segments) > 1 or TIME_STEPS_ATTR in f.attrs else None
