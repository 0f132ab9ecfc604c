"""The paper's outputs (Fig. 2, 3, 4 and Table 2) from a run directory, headless.

Reads files only (summary.json, ``sample_<seed>/shear_series.h5``, ``sample_<seed>/states.h5``)
and never imports the solver. Plots use Matplotlib's object API on the Agg canvas (no pyplot,
no display). The 3-D renders of Fig. 2 and Fig. 3 come from :mod:`tcd.render`, imported only
when a states file is there, because it needs Taichi.

Peak detection: the shear stress of Contact Dynamics fluctuates from step to step, so the peak is
taken on a centred moving average over a window in displacement units (:func:`smooth`); the
displacement at the peak is the imposed displacement at that index (:func:`peak_of`). The
window is the series' ``smoothing_window`` attribute, else :data:`DEFAULT_SMOOTHING_WINDOW`.
The runner's ``tau_peak``/``d_peak`` attributes, when present, are the values shown.

Invariants: every output file is replaced atomically (:func:`tcd.io.atomic_path`); a sample
without a readable series is skipped with a :class:`FigureWarning`; a run directory with no
usable sample raises ValueError naming the directory; a failing render is skipped with a
warning and the other outputs are still written.

Usage: ``python -m tcd.figures RUN_DIR [RUN_DIR ...] [--out OUT_DIR]`` (several run
directories: the parts of one study, split with ``tcd run --seeds``; ``--out`` is then needed).
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import re
import textwrap
import warnings
from pathlib import Path

import h5py
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from . import io
from . import observables as obs
from .config import ShearStage

#: paper Table 2 (MPa, mm): the experiments and the paper's own simulations
EXPERIMENT, PAPER_SIMULATION = obs.PAPER_EXPERIMENT, obs.PAPER_SIMULATION
#: moving-average window (m of imposed displacement) when the series does not give one:
#: the scenario's default, ``[[stage]] smoothing_window_mm`` of a shear stage (0.1 mm)
DEFAULT_SMOOTHING_WINDOW = ShearStage.model_fields["smoothing_window_mm"].default * 1e-3
#: end of the imposed displacement in the paper (m); Fig. 4's x range
DISPLACEMENT_END = 2.5e-3

SERIES_NAME = "shear_series.h5"
STATES_NAME = "states.h5"
SUMMARY_NAME = "summary.json"

_RC = {"font.size": 10, "axes.labelsize": 11, "axes.titlesize": 11, "legend.fontsize": 9,
       "xtick.labelsize": 9.5, "ytick.labelsize": 9.5, "axes.linewidth": 0.8,
       "font.family": "DejaVu Sans", "pdf.fonttype": 42}


class FigureWarning(UserWarning):
    """A sample or a figure was skipped; the other outputs are still written."""


# --- pure helpers ----------------------------------------------------------------------------
# smooth and peak_of are the run's own (tcd.observables): Fig. 4 and summary.json agree
smooth = obs.smooth
peak_of = obs.peak_of


def _relative_error(value: float, reference: float) -> float:
    return (value - reference) / reference if reference else math.nan


def is_paper_test(summary: dict | None, samples=()) -> bool:
    """Whether the run is the paper's Leutner test, to be compared with Table 2's experiments:
    its summary's `paper_test` (written since session 49); for an older summary, or none, a
    test that reached half the paper's 2.5 mm (the series of `samples`, SampleCurves)."""
    flag = (summary or {}).get("paper_test")
    if isinstance(flag, bool):
        return flag
    if summary is not None and not samples:
        return True
    d_end = max((float(np.nanmax(s.displacement)) for s in samples), default=math.nan)
    return bool(d_end >= 0.5 * DISPLACEMENT_END)


def not_compared_note(summary: dict | None) -> str:
    """The line Table 2 shows for a run that is not the paper's test (how it differs)."""
    differences = [str(x) for x in (summary or {}).get("paper_test_differences") or []]
    return ("Not compared with the paper's experiments: this test is not its Leutner test"
            + (f" ({'; '.join(differences)})." if differences else "."))


def table2_rows(summary: dict, paper_test: bool | None = None) -> list[dict]:
    """Rows of the paper's Table 2 with this run added; for a run that is not the paper's
    Leutner test (`paper_test`, default :func:`is_paper_test` of the summary), the run's row
    alone, without relative errors.

    Each row: ``label``, ``tau_MPa``, ``d_mm``, ``tau_std_MPa``, ``d_std_mm`` (NaN where not
    applicable), ``n_samples`` (None for the experiments), ``tau_rel_error``, ``d_rel_error``
    (signed, ``(value - experiment) / experiment``; NaN for the experiments row).
    The run's mean and std come from ``summary["mean"]``/``["std"]``, else from its samples
    (population std, as the runner writes it).
    """
    experiment = {**EXPERIMENT, **(summary.get("experiment") or {})}
    paper = {**PAPER_SIMULATION, **(summary.get("paper_simulation") or {})}
    tau_exp = obs.as_number(experiment["tau_peak_MPa"])
    d_exp = obs.as_number(experiment["d_peak_mm"])
    samples = summary.get("samples") or []
    mean, std = summary.get("mean") or {}, summary.get("std") or {}

    def run_stat(key):
        m, s = obs.as_number(mean.get(key)), obs.as_number(std.get(key))
        values = np.array([obs.as_number(smp.get(key)) for smp in samples], dtype=float)
        values = values[np.isfinite(values)]
        if not math.isfinite(m) and values.size:
            m = float(values.mean())
        if not math.isfinite(s) and values.size > 1:
            s = float(values.std())     # population std, as the runner's summary
        return m, s

    tau_run, tau_std = run_stat("tau_peak_MPa")
    d_run, d_std = run_stat("d_peak_mm")
    n = len(samples)

    def row(label, tau, d, tau_s=math.nan, d_s=math.nan, n_samples=None, reference=True):
        return {"label": label, "tau_MPa": tau, "d_mm": d, "tau_std_MPa": tau_s,
                "d_std_mm": d_s, "n_samples": n_samples,
                "tau_rel_error": _relative_error(tau, tau_exp) if reference else math.nan,
                "d_rel_error": _relative_error(d, d_exp) if reference else math.nan}

    if paper_test is None:
        paper_test = is_paper_test(summary)
    if not paper_test:
        label = (f"tcd (this run, mean ± std of {n} samples)" if n != 1
                 else "tcd (this run, one sample)")
        return [row(label, tau_run, d_run, *((tau_std, d_std) if n != 1 else ()),
                    n_samples=n, reference=False)]
    return [
        row("experiments", tau_exp, d_exp, reference=False),
        row("paper simulations (LMGC90)", obs.as_number(paper["tau_peak_MPa"]),
            obs.as_number(paper["d_peak_mm"]), n_samples=5),
        row(f"tcd (this run, mean ± std of {n} samples)", tau_run, d_run, tau_std, d_std, n)
        if n != 1 else
        # one sample has no spread: its std (0 in the runner's summary) is not shown
        row("tcd (this run, one sample)", tau_run, d_run, n_samples=1),
    ]


# --- reading a run directory -----------------------------------------------------------------
@dataclasses.dataclass
class SampleCurves:
    """The shear series of one sample, in SI units, with its peak."""
    seed: str
    directory: Path
    time: np.ndarray            # (T,) s
    displacement: np.ndarray    # (T,) m, imposed on the upper ring
    stress: np.ndarray          # (T,) Pa
    smoothed: np.ndarray        # (T,) Pa, :func:`smooth` over `window`
    window: float               # m
    tau_peak: float             # Pa
    d_peak: float               # m
    peak_index: int
    series: dict                # every dataset of the series file
    # a shear stopped before its end (`load_stopped_sample`: its series so far, from its
    # checkpoint), and the run it went on from (`tcd run --from`), as its checkpoint has it
    stopped: bool = False
    branched_from: dict | None = None

    @property
    def peak_time(self) -> float:
        return float(self.time[self.peak_index]) if self.time.size else math.nan

    @property
    def peak_at_end(self) -> bool:
        """The peak lies within half a smoothing window of the series' last point (its
        average reaches the end): the curve was not seen to fall from it, no failure
        (:func:`tcd.observables.peak_at_end`)."""
        return obs.peak_at_end(self.displacement, self.d_peak, self.window)


def peak_at_end_note(samples: list[SampleCurves]) -> str:
    """The sentence under Table 2 naming the samples whose curve still rose at its end
    (their "peak" the last point, not a failure), or "" when every sample peaked before."""
    ends = [s for s in samples if s.peak_at_end]
    if not ends:
        return ""
    half = " / ".join(sorted({f"{0.5 * s.window * 1e3:g}" for s in ends}))
    if len(ends) == 1:
        return (f"In 1 of the {len(samples)} samples (sample {ends[0].seed}) the stress still "
                f"rose at the end of its curve: its peak lies within half a smoothing window "
                f"({half} mm) of the last point, so its τ and d are that end, not a failure; a "
                "longer test would find its peak there or later, as high or higher.")
    return (f"In {len(ends)} of the {len(samples)} samples (samples "
            f"{', '.join(str(s.seed) for s in ends)}) the stress still rose at the end of their "
            f"curves: each peak lies within half a smoothing window ({half} mm) of its curve's "
            "last point, so their τ and d are those ends, not failures; a longer test would "
            "find each peak there or later, as high or higher.")


def left_out_note(skipped: list, counted: int) -> str:
    """The sentence under Table 2 naming the samples left out of it and of the figures
    (`skipped`: (seed, reason) from :func:`load_runs`), or "" when none was: a reader of the
    table alone must not take the mean of some samples for the study's."""
    if not skipped:
        return ""

    def why(exc):
        return ("no series file yet: stopped or still running" if isinstance(exc, FileNotFoundError)
                else "its series unreadable")
    names = "; ".join(f"sample {seed} ({why(exc)})" for seed, exc in skipped)
    return (f"Left out of this table and the figures: {names}. The means are over the other "
            f"{counted} sample{'s' if counted != 1 else ''}; `tcd info RUN_DIR` says where each "
            "sample stands.")


def _sample_dirs(run_dir: Path, summary: dict | None) -> list[tuple[str, Path]]:
    """(seed, directory) for the summary's samples first, then any other sample_* folder."""
    found, seen = [], set()
    for smp in (summary or {}).get("samples") or []:
        seed = str(smp.get("seed"))
        if seed not in seen:
            seen.add(seed)
            found.append((seed, run_dir / f"sample_{seed}"))
    others = [p for p in run_dir.glob("sample_*") if p.is_dir()]
    for path in sorted(others, key=lambda p: _seed_key(p.name[len("sample_"):])):
        seed = path.name[len("sample_"):]
        if seed not in seen:
            seen.add(seed)
            found.append((seed, path))
    return found


def _seed_value(seed):
    """A seed read as text (a folder name, a summary): an int where it is one, else the text."""
    return int(seed) if re.fullmatch(r"-?\d+", str(seed)) else seed


def _seed_key(seed: str):
    value = _seed_value(seed)
    return (0, value, "") if isinstance(value, int) else (1, 0, seed)


def _series_attrs(path: Path) -> dict:
    with h5py.File(path, "r") as f:
        return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}


def load_sample(seed: str, directory: Path) -> SampleCurves:
    """Read ``directory/shear_series.h5``; raise FileNotFoundError/ValueError if unusable."""
    path = directory / SERIES_NAME
    return _curves(seed, directory, io.read_series(path), _series_attrs(path), path)


def load_stopped_sample(seed: str, directory: Path, batch: Path | None = None) -> SampleCurves:
    """A shear stopped before its end (interrupted, or still running): its series so far,
    from ``directory/checkpoint.h5`` (the one a `--resume` continues from) or, for a sample of
    a batch (`tcd run --batch`), from the batch's checkpoint `batch`, smoothed over its
    scenario's window; `stopped` is set. Raises FileNotFoundError/ValueError when there is no
    such checkpoint, or it was written outside a shear stage."""
    path = directory / "checkpoint.h5"
    if batch is not None and not path.exists() and batch.exists():
        series, window, meta = io.checkpoint_shear_series(batch, seed)
        path = batch
    else:
        series, window, meta = io.checkpoint_shear_series(path)
    window = obs.as_number(window)
    curves = _curves(seed, directory, series, {"smoothing_window": window * 1e-3}, path)
    branch = (meta.get("result") or {}).get("branched_from")
    return dataclasses.replace(curves, stopped=True, branched_from=(
        branch[-1] if isinstance(branch, list) and branch and isinstance(branch[-1], dict)
        else None))


def _curves(seed: str, directory: Path, series: dict, attrs: dict, path: Path) -> SampleCurves:
    """SampleCurves of a shear's `series` (read from `path`) and its file's `attrs` (the
    smoothing window, and the runner's peak where it wrote one)."""
    for key in ("displacement", "shear_stress"):
        if key not in series:
            raise ValueError(f"{path}: series without {key!r}")
    length = np.shape(series["displacement"])[:1]
    for key, values in series.items():     # one number per record, as the runner writes them
        values = np.asarray(values)
        if values.dtype.kind not in "biuf" or values.ndim != 1 or values.shape != length:
            raise ValueError(f"{path}: series {key!r} has shape {values.shape} and dtype "
                             f"{values.dtype}, expected {length[0] if length else 'N'} numbers "
                             "(as 'displacement')")
    displacement = np.asarray(series["displacement"], dtype=float)
    stress = np.asarray(series["shear_stress"], dtype=float)
    if displacement.size == 0:
        raise ValueError(f"{path}: empty series")
    if not np.any(np.isfinite(stress)):
        raise ValueError(f"{path}: series 'shear_stress' holds no finite value")
    time = np.asarray(series.get("time", np.arange(displacement.size)), dtype=float)
    window = obs.as_number(attrs.get("smoothing_window"))
    if not window > 0:
        window = DEFAULT_SMOOTHING_WINDOW
    smoothed = smooth(stress, displacement, window)
    tau_peak, d_peak, index = peak_of(displacement, stress, window)
    tau_attr, d_attr = obs.as_number(attrs.get("tau_peak")), obs.as_number(attrs.get("d_peak"))
    if math.isfinite(tau_attr) and math.isfinite(d_attr):
        # the runner's numbers are the ones reported; the index follows its displacement
        tau_peak, d_peak = tau_attr, d_attr
        index = int(np.argmin(np.abs(displacement - d_attr)))
    return SampleCurves(seed, directory, time, displacement, stress, smoothed, window,
                        tau_peak, d_peak, index, series)


def load_run(run_dir, skipped: list | None = None, *,
             stopped: bool = False) -> tuple[dict | None, list[SampleCurves]]:
    """(summary or None, usable samples); unusable samples are skipped with a warning, or,
    given a list `skipped`, appended to it as (seed, reason) for the caller to report.
    `stopped`: a sample without its series file but with a shear's checkpoint is read as far
    as it went (:func:`load_stopped_sample`; `tcd compare`, not a study's Table 2).

    Raises FileNotFoundError if run_dir is not a directory, ValueError if no sample is usable.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: run directory not found")
    summary = None
    summary_path = run_dir / SUMMARY_NAME
    if summary_path.exists():
        try:
            summary = json.loads(summary_path.read_text(encoding="utf-8"))
            problem = _summary_problem(summary)
            if problem:
                raise ValueError(problem)
        except ValueError as exc:
            summary = None
            warnings.warn(f"{summary_path}: unreadable ({exc}); using the series only",
                          FigureWarning, stacklevel=2)
    samples = []
    for seed, directory in _sample_dirs(run_dir, summary):
        try:
            if stopped and not (directory / SERIES_NAME).exists():
                samples.append(load_stopped_sample(seed, directory,
                                                   run_dir / "batch_checkpoint.h5"))
            else:
                samples.append(load_sample(seed, directory))
        except (OSError, ValueError, KeyError) as exc:
            if skipped is None:
                warnings.warn(f"sample {seed} skipped: {_reason(exc)}", FigureWarning, stacklevel=2)
            else:
                skipped.append((seed, exc))
    if not samples:
        raise ValueError(f"{run_dir}: no usable sample (no readable "
                         f"sample_<seed>/{SERIES_NAME}); nothing to plot")
    return summary, samples


def _summary_problem(summary) -> str | None:
    """What makes a parsed summary.json unusable here (None when it is usable): the shape
    `tcd run` writes, an object whose `samples` is a list of objects and whose `mean`, `std`,
    `experiment` and `paper_simulation` are objects, where present."""
    if not isinstance(summary, dict):
        return f"not a JSON object (a {type(summary).__name__})"
    samples = summary.get("samples")
    if samples is not None and not (isinstance(samples, list)
                                    and all(isinstance(smp, dict) for smp in samples)):
        return "its 'samples' is not a list of objects"
    for key in ("mean", "std", "experiment", "paper_simulation"):
        if summary.get(key) is not None and not isinstance(summary[key], dict):
            return f"its {key!r} is not an object"
    return None


def summary_from_samples(samples: list[SampleCurves]) -> dict:
    """A minimal summary (samples, mean, std) from the series when summary.json is missing."""
    # a seed read from a folder name is text: a number, as the runner's summaries write it
    rows = [{"seed": _seed_value(s.seed), "tau_peak_MPa": s.tau_peak * 1e-6,
             "d_peak_mm": s.d_peak * 1e3} for s in samples]
    out = {"samples": rows, "mean": {}, "std": {}}
    for key in ("tau_peak_MPa", "d_peak_mm"):
        values = np.array([r[key] for r in rows])
        out["mean"][key] = float(values.mean())
        out["std"][key] = float(values.std()) if values.size > 1 else math.nan
    return out


#: the scenario keys that may differ between the runs of one study (--seeds splits it): they
#: change no number of a sample (a sample's numbers depend on its seed and the physics only)
STUDY_FREE_KEYS = ("seeds", "description", "name", "output")
STUDY_SUMMARY_NAME = "study_summary.json"


def _reason(exc: BaseException) -> str:
    """Why a sample was skipped, in one line: a missing file as `PATH: what is missing` (it
    was Python's "[Errno 2] no such tcd series file: 'PATH'")."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def _scenario_of(run_dir: Path) -> dict | None:
    """The run's scenario.toml as its checked configuration, every default filled in (so
    that a key written out with its default value equals a key left out, as for --resume),
    as a dict (None where it is missing or unreadable). A scenario that no longer validates
    (a run of an older tcd) is compared as written."""
    import tomllib
    from .config import ScenarioError, parse_scenario
    path = run_dir / "scenario.toml"
    try:
        text = path.read_text(encoding="utf-8")
        tomllib.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        # its samples keep the scenario they ran (states.h5, checkpoint.h5): `tcd compare`
        # said two runs' scenarios did not differ when one's scenario.toml was gone
        # (session 72's review)
        text = _recorded_scenario_text(run_dir)
        if text is None:
            return None
    try:
        data = parse_scenario(text, str(path), resolve_samples=False).model_dump(
            mode="json", by_alias=True, exclude={"text", "source"})
    except ScenarioError:
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError:
            return None
    return {k: v for k, v in data.items() if k not in STUDY_FREE_KEYS}


def _scenario_base(run_dir: Path) -> Path | None:
    """The folder of the scenario file the run read, as its run.json names it (runs since
    session 58; None before): where its relative sample paths lead."""
    try:
        source = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))["scenario_file"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return Path(source).parent if isinstance(source, str) and source else None


def _recorded_scenario_text(run_dir: Path) -> str | None:
    """The scenario text a sample of `run_dir` recorded (its states.h5, else its checkpoint;
    None where none is readable)."""
    for sample in sorted(run_dir.glob("sample_*")):
        for name in ("states.h5", "checkpoint.h5"):
            try:
                if name == "states.h5":
                    import h5py
                    with h5py.File(sample / name, "r") as f:
                        text = io._attr_text(f, "scenario")
                else:
                    text = io.checkpoint_meta(sample / name)[0].get("scenario_text", "")
            except (OSError, ValueError, KeyError, RuntimeError, AttributeError):
                continue
            if isinstance(text, str) and text.strip():
                return text
    return None


def scenarios_of(run_dirs) -> list[dict | None]:
    """:func:`_scenario_of` of each run, to compare them: where every run names the scenario
    file it read (run.json, since session 58), a relative sample path is read from that file's
    folder, as the run read it, so that two spellings of one file are one setting; else every
    path is compared as written (an older run's folder is not known)."""
    scenarios = [_scenario_of(Path(d)) for d in run_dirs]
    bases = [_scenario_base(Path(d)) for d in run_dirs]
    if any(b is None for b, sc in zip(bases, scenarios) if sc is not None):
        return scenarios
    for base, scenario in zip(bases, scenarios):
        stages = (scenario or {}).get("stage")
        for stage in stages if isinstance(stages, list) else []:
            if isinstance(stage, dict) and isinstance(stage.get("sample"), str) and stage["sample"]:
                stage["sample"] = os.path.normpath(base / stage["sample"])
    return scenarios


def _backend_of(run_dir: Path) -> dict | None:
    try:
        record = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict):
        return None
    return {k: record.get(k) for k in ("arch", "precision")}


def check_one_study(run_dirs: list[Path]) -> None:
    """Refuse run directories that are not parts of one study: a scenario other than the
    first run's (:data:`STUDY_FREE_KEYS` aside) raises ValueError naming what differs; runs on
    different backends, or without a readable scenario.toml, give a FigureWarning."""
    first = run_dirs[0]
    reference, *others = scenarios_of(run_dirs)
    backend = _backend_of(first)
    for other, scenario in zip(run_dirs[1:], others):
        if reference is None or scenario is None:
            missing = first if reference is None else other
            warnings.warn(f"{missing / 'scenario.toml'} missing or unreadable: cannot check that "
                          f"{first} and {other} ran the same scenario", FigureWarning,
                          stacklevel=3)
        else:
            changed = io.differences(reference, scenario, base=1)
            if changed:
                raise ValueError(f"{other} ran another scenario than {first} "
                                 f"({io.shown_differences(changed)}): its samples are not part "
                                 "of the same study")
        theirs = _backend_of(other)
        if backend and theirs and backend != theirs:
            warnings.warn(f"{first} ran on {backend['arch']}/{backend['precision']} and "
                          f"{other} on {theirs['arch']}/{theirs['precision']}: the samples "
                          "differ at the level of the solver tolerance", FigureWarning,
                          stacklevel=3)


def merge_summaries(parts: list[tuple[Path, dict]]) -> dict:
    """One study summary from the summaries of its runs: the samples of all (by seed), their
    mean, population std and relative errors (:func:`tcd.observables.study_statistics`, as
    the runner's summary) and the runs it came from. A seed in two runs raises ValueError."""
    owner, samples = {}, []
    for run_dir, summary in parts:
        for smp in summary.get("samples") or []:
            seed = str(smp.get("seed"))
            if seed in owner:
                raise ValueError(f"sample {seed} is in both {owner[seed]} and {run_dir}: give "
                                 "each sample once")
            owner[seed] = run_dir
            samples.append(smp)
    samples.sort(key=lambda smp: _seed_key(str(smp.get("seed"))))
    first = parts[0][1]
    experiment = {**EXPERIMENT, **(first.get("experiment") or {})}
    mean, std, relative = obs.study_statistics(samples, experiment)
    # the parts' tests (one scenario): the paper's unless a part says otherwise; parts written
    # before session 49 do not say, and the merged summary does not either (is_paper_test then
    # judges by the samples' range, as for one such run)
    flags = [s.get("paper_test") for _, s in parts if isinstance(s.get("paper_test"), bool)]
    paper = all(flags)
    differences = list(dict.fromkeys(str(x) for _, s in parts
                                     for x in s.get("paper_test_differences") or []))
    said = {"paper_test": paper, "paper_test_differences": [] if paper else differences} \
        if flags else {}
    return {"scenario": first.get("scenario"), "merged_from": [os.fspath(p) for p, _ in parts],
            "samples": samples, "mean": mean, "std": std, **said,
            "experiment": experiment if paper else None,
            "paper_simulation": ({**PAPER_SIMULATION, **(first.get("paper_simulation") or {})}
                                 if paper else None),
            "relative_error": relative if paper else None,
            "wall_time_s": {k: v for _, s in parts for k, v in (s.get("wall_time_s") or {}).items()
                            if k.startswith("sample_")}}


def _as_run_dirs(run_dirs) -> list[Path]:
    """One path or a list of them, as a list of Paths."""
    if isinstance(run_dirs, (str, os.PathLike)):
        return [Path(run_dirs)]
    return [Path(p) for p in run_dirs]


def load_runs(run_dirs, skipped: list | None = None) -> tuple[dict | None, list[SampleCurves]]:
    """Like :func:`load_run` for one or several run directories of one study (a study split
    with ``tcd run --seeds``): the samples of all of them and their merged summary. Each
    sample skipped gives a warning, and with a list `skipped` is appended to it as (seed,
    reason) too.

    Raises ValueError for runs of different scenarios, a seed found twice, or a run without a
    usable sample; FileNotFoundError for a missing directory.
    """
    run_dirs = _as_run_dirs(run_dirs)
    if not run_dirs:
        raise ValueError("no run directory given")
    if len(run_dirs) == 1:
        own: list = []
        try:
            summary, samples = load_run(run_dirs[0], own)
        finally:                         # warned even when no sample is left (ValueError)
            for seed, exc in own:
                warnings.warn(f"sample {seed} skipped: {_reason(exc)}", FigureWarning, stacklevel=2)
            if skipped is not None:
                skipped += own
        return summary, samples
    for run_dir in run_dirs:
        if not run_dir.is_dir():
            raise FileNotFoundError(f"{run_dir}: run directory not found")
    check_one_study(run_dirs)
    parts, samples, found_skipped = [], [], []
    for run_dir in run_dirs:
        summary, found = load_run(run_dir, found_skipped)
        parts.append((run_dir, summary if summary is not None else summary_from_samples(found)))
        samples += found
    merged = merge_summaries(parts)     # raises on a seed found twice
    samples.sort(key=lambda s: _seed_key(s.seed))
    # a seed unfinished in one part (an interrupted invocation) and finished in another is
    # not skipped: only the seeds missing from the study are reported
    have = {str(s.seed) for s in samples}
    for seed, exc in found_skipped:
        if str(seed) not in have:
            warnings.warn(f"sample {seed} skipped: {_reason(exc)}", FigureWarning, stacklevel=2)
            if skipped is not None:
                skipped.append((seed, exc))
    return merged, samples


# --- writing ---------------------------------------------------------------------------------
def _new_figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), dpi=150, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: Path, written: list) -> None:
    with io.atomic_path(path) as tmp:
        fmt = path.suffix.lstrip(".")
        io.save_figure(fig, tmp, fmt, dpi=fig.dpi)
    written.append(path)


def _write_text(path: Path, text: str, written: list) -> None:
    with io.atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
    written.append(path)


def _colors(n: int):
    import matplotlib
    cmap = matplotlib.colormaps["tab10"]
    return [cmap(k % 10) for k in range(n)]


def figure_stress_displacement(samples: list[SampleCurves], out_png: Path, written: list,
                               pdf: bool = True, paper_test: bool | None = None) -> None:
    """Paper Fig. 4: shear stress against imposed displacement, one line per sample; the
    experiments' and the paper's peaks where the run is the paper's test (`paper_test`,
    default: :func:`is_paper_test` of the samples)."""
    import matplotlib
    with matplotlib.rc_context(_RC):
        fig = _new_figure(7.2, 4.3)
        ax = fig.add_subplot()
        # another test than the paper's is drawn over its own range, without the experiments'
        # peak at 2.37 mm (not its test; it would squeeze a short test into a corner)
        d_end = max(float(np.nanmax(s.displacement)) for s in samples)
        leutner = is_paper_test(None, samples) if paper_test is None else paper_test
        top = EXPERIMENT["tau_peak_MPa"] if leutner else 0.0
        for sample, color in zip(samples, _colors(len(samples))):
            d_mm = sample.displacement * 1e3
            ax.plot(d_mm, sample.stress * 1e-6, color=color, lw=0.5, alpha=0.25, zorder=1)
            ax.plot(d_mm, sample.smoothed * 1e-6, color=color, lw=1.6, zorder=2,
                    label=f"sample {sample.seed}")
            ax.plot(sample.d_peak * 1e3, sample.tau_peak * 1e-6,
                    ">" if sample.peak_at_end else "o", ms=6, mfc="white",
                    mec=color, mew=1.6, zorder=4, clip_on=False)
            top = max(top, float(np.nanmax(sample.smoothed)) * 1e-6)
        d_exp, tau_exp = EXPERIMENT["d_peak_mm"], EXPERIMENT["tau_peak_MPa"]
        if leutner:
            ax.plot([d_exp, d_exp], [0.0, tau_exp], "k--", lw=0.8, zorder=3)
            ax.plot([0.0, d_exp], [tau_exp, tau_exp], "k--", lw=0.8, zorder=3)
            ax.plot(d_exp, tau_exp, "*", color="k", ms=14, zorder=5,
                    label="experiments (mean of 5 cores)")
            ax.plot(PAPER_SIMULATION["d_peak_mm"], PAPER_SIMULATION["tau_peak_MPa"], "D",
                    color="0.35", mfc="none", ms=7, mew=1.4, zorder=5,
                    label="paper simulations (LMGC90, mean)")
        ax.plot([], [], "o", ms=6, mfc="white", mec="0.3", mew=1.6, label="peak of each sample")
        if any(s.peak_at_end for s in samples):
            ax.plot([], [], ">", ms=6, mfc="white", mec="0.3", mew=1.6,
                    label="end of a curve still rising\n(no failure by then)")
        bottom = min(0.0, min(float(np.nanmin(s.smoothed)) for s in samples) * 1e-6)
        ax.set_xlim(0.0, (max(DISPLACEMENT_END, d_end) if leutner else d_end) * 1e3)
        ax.set_ylim(bottom, 1.12 * top if top > 0 else None)
        ax.set_xlabel("Imposed displacement d (mm)")
        ax.set_ylabel("Shear stress τ (MPa)")
        ax.grid(True, lw=0.4, alpha=0.4)
        ax.tick_params(direction="in", top=True, right=True)
        window_mm = samples[0].window * 1e3
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False,
                  title=f"moving average over {window_mm:g} mm\n(raw signal faint)",
                  title_fontsize=8.5, alignment="left")
        _save(fig, out_png, written)
        if pdf:
            _save(fig, out_png.with_suffix(".pdf"), written)


def _fmt(value: float, digits: int, std: float = math.nan) -> str:
    if not math.isfinite(value):
        return "–"
    text = f"{value:.{digits}f}"
    if math.isfinite(std):
        text += f" ± {std:.{digits}f}"
    return text


def _fmt_error(value: float) -> str:
    return f"{100.0 * value:+.1f} %" if math.isfinite(value) else "–"


def table2_markdown(rows: list[dict], note: str = "", footnote: str = "") -> str:
    """Table 2 in Markdown; `note`: a run not compared with the experiments
    (:func:`not_compared_note`), under the title, and no relative-error columns; `footnote`:
    a paragraph under the table (:func:`peak_at_end_note`)."""
    tail = ["", footnote] if footnote else []
    if note:
        lines = ["Table 2. Average values of shear stress τ and peak displacement d at failure "
                 "of this run.", "", note, "", "| | τ [MPa] | d [mm] |", "|---|---|---|"]
        lines += [f"| {r['label']} | {_fmt(r['tau_MPa'], 3, r['tau_std_MPa'])} | "
                  f"{_fmt(r['d_mm'], 2, r['d_std_mm'])} |" for r in rows]
        return "\n".join(lines + tail) + "\n"
    lines = ["Table 2. Average values of shear stress τ and peak displacement d at failure "
             "through the experiments and the simulations (relative error to the experiments).",
             "",
             "| | τ [MPa] | d [mm] | rel. error τ | rel. error d |",
             "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['label']} | {_fmt(r['tau_MPa'], 3, r['tau_std_MPa'])} | "
                     f"{_fmt(r['d_mm'], 2, r['d_std_mm'])} | {_fmt_error(r['tau_rel_error'])} | "
                     f"{_fmt_error(r['d_rel_error'])} |")
    return "\n".join(lines + tail) + "\n"


def table2_csv(rows: list[dict]) -> str:
    import io as _stdio
    keys = ["label", "tau_MPa", "tau_std_MPa", "d_mm", "d_std_mm", "n_samples",
            "tau_rel_error", "d_rel_error"]
    buffer = _stdio.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(keys)
    for r in rows:
        writer.writerow(["" if r[k] is None or (isinstance(r[k], float) and math.isnan(r[k]))
                         else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k])
                         for k in keys])
    return buffer.getvalue()


def figure_table2(rows: list[dict], out_png: Path, written: list, note: str = "",
                  footnote: str = "") -> None:
    """Table 2 as an image: a plain three-rule table (top, below the header, bottom). With a
    `note` (a run not compared with the experiments: :func:`not_compared_note`) the table has
    no relative-error columns and the note, wrapped, stands under the title; a `footnote`
    (:func:`peak_at_end_note`), wrapped, stands under the table."""
    import matplotlib
    compared = not note
    header = ["", "τ [MPa]", "d [mm]"] + (["rel. error τ", "rel. error d"] if compared else [])
    cells = [[r["label"].replace(" (this run, ", "\n(this run, "),
              _fmt(r["tau_MPa"], 3, r["tau_std_MPa"]), _fmt(r["d_mm"], 2, r["d_std_mm"])]
             + ([_fmt_error(r["tau_rel_error"]), _fmt_error(r["d_rel_error"])] if compared else [])
             for r in rows]
    lines = textwrap.wrap(note, 120) if note else []
    if compared:        # the layout of every figure before session 49, to the byte
        height, axes, widths = 2.3, (0.02, 0.04, 0.96, 0.70), [0.36, 0.17, 0.15, 0.16, 0.16]
    else:               # inches: title and note lines above, rows of 0.4 in, 0.09 in below
        above, table_h = 0.42 + 0.14 * len(lines), 0.4 * (len(rows) + 1)
        height = above + table_h + 0.09
        axes, widths = (0.02, 0.09 / height, 0.96, table_h / height), [0.52, 0.24, 0.24]
    foot = textwrap.wrap(footnote, 120) if footnote else []
    foot_h = 0.14 * len(foot) + 0.12 if foot else 0.0          # inches added at the bottom
    scale = height / (height + foot_h)                         # the figure above, squeezed
    height += foot_h
    axes = (axes[0], axes[1] * scale + foot_h / height, axes[2], axes[3] * scale)
    with matplotlib.rc_context(_RC):
        fig = Figure(figsize=(8.2, height), dpi=150)
        FigureCanvasAgg(fig)
        ax = fig.add_axes(axes)
        ax.axis("off")
        table = ax.table(cellText=cells, colLabels=header, loc="upper center",
                         cellLoc="center", colLoc="center", colWidths=widths, bbox=(0, 0, 1, 1))
        table.auto_set_font_size(False)
        table.set_fontsize(10)
        for (row, col), cell in table.get_celld().items():
            cell.set_edgecolor("none")
            if row == 0:
                cell.set_text_props(weight="bold")
            if col == 0:
                cell.set_text_props(ha="left")
                cell.PAD = 0.02
        n = len(rows) + 1
        for y, lw in ((1.0, 1.2), ((n - 1) / n, 0.7), (0.0, 1.2)):
            ax.plot([0, 1], [y, y], color="k", lw=lw, transform=ax.transAxes, clip_on=False)
        if compared:
            fig.text(0.02, 1.0 - 0.04 * scale, "Table 2. Shear stress τ and displacement d at "
                     "failure: experiments and simulations", ha="left", va="top",
                     fontsize=10.5, weight="bold")
            fig.text(0.02, 1.0 - 0.14 * scale, "relative error = (simulation − experiment) / "
                     "experiment", ha="left", va="top", fontsize=8.5, color="0.3")
        else:
            fig.text(0.02, 1.0 - 0.09 / height, "Table 2. Shear stress τ and displacement d at "
                     "failure: this run", ha="left", va="top", fontsize=10.5, weight="bold")
            fig.text(0.02, 1.0 - 0.33 / height, "\n".join(lines), ha="left", va="top",
                     fontsize=8.0, color="0.3", linespacing=1.15)
        if foot:
            fig.text(0.02, (foot_h - 0.06) / height, "\n".join(foot), ha="left", va="top",
                     fontsize=8.0, color="0.3", linespacing=1.15)
        _save(fig, out_png, written)


def _bonds_total(sample: SampleCurves, summary: dict | None) -> float:
    """Initial bond count: intact + broken in the series (constant), else the summary's."""
    s = sample.series
    if "bonds_intact" in s and len(s["bonds_intact"]):
        return float(sum(float(s[k][0]) for k in
                         ("bonds_intact", "bonds_broken_tension", "bonds_broken_shear") if k in s))
    for smp in (summary or {}).get("samples") or []:
        if str(smp.get("seed")) == sample.seed and obs.as_number(smp.get("bonds_total")) > 0:
            return obs.as_number(smp["bonds_total"])
    return math.nan


def figure_bonds_broken(samples: list[SampleCurves], summary: dict | None, out_png: Path,
                        written: list) -> bool:
    """Broken bonds against displacement: counts (left) and fraction of the initial bonds
    (right); total solid, in tension dashed, in shear dotted, one colour per sample."""
    import matplotlib
    import matplotlib.ticker
    from matplotlib.lines import Line2D
    usable = [s for s in samples
              if "bonds_broken_tension" in s.series and "bonds_broken_shear" in s.series]
    if not usable:
        warnings.warn("bonds_broken.png skipped: no series has bonds_broken_tension/shear",
                      FigureWarning, stacklevel=3)
        return False
    with matplotlib.rc_context(_RC):
        fig = _new_figure(10.0, 4.0)
        ax_count, ax_frac = fig.subplots(1, 2)
        for sample, color in zip(usable, _colors(len(usable))):
            d_mm = sample.displacement * 1e3
            tension = np.asarray(sample.series["bonds_broken_tension"], dtype=float)
            shear = np.asarray(sample.series["bonds_broken_shear"], dtype=float)
            total = tension + shear
            initial = _bonds_total(sample, summary)
            for ax, scale in ((ax_count, 1.0), (ax_frac, 1.0 / initial if initial > 0 else None)):
                if scale is None:
                    continue
                ax.plot(d_mm, total * scale, color=color, lw=1.6, label=f"sample {sample.seed}")
                ax.plot(d_mm, tension * scale, color=color, lw=1.0, ls="--")
                ax.plot(d_mm, shear * scale, color=color, lw=1.0, ls=":")
        for ax, label in ((ax_count, "Broken bonds (count)"),
                          (ax_frac, "Broken bonds / initial bonds")):
            ax.set_xlim(0.0, DISPLACEMENT_END * 1e3)
            ax.set_ylim(bottom=0.0)
            ax.set_xlabel("Imposed displacement d (mm)")
            ax.set_ylabel(label)
            ax.grid(True, lw=0.4, alpha=0.4)
            ax.tick_params(direction="in", top=True, right=True)
        ax_frac.yaxis.set_major_formatter(matplotlib.ticker.PercentFormatter(1.0))
        ax_count.set_title("(a) counts", loc="left")
        ax_frac.set_title("(b) fraction of the initial bonds", loc="left")
        styles = [Line2D([], [], color="0.2", lw=1.6, label="total"),
                  Line2D([], [], color="0.2", lw=1.0, ls="--", label="in tension"),
                  Line2D([], [], color="0.2", lw=1.0, ls=":", label="in shear")]
        handles, _ = ax_count.get_legend_handles_labels()
        fig.legend(handles=handles + styles, loc="outside right upper", frameon=False)
        _save(fig, out_png, written)
    return True


def _frame_stages(states_path: Path) -> list[tuple[float, str]]:
    """(time, stage) of every frame of a states file, in frame order."""
    io.frame_count(states_path)  # validates the file (schema, kind, frames group)
    with h5py.File(states_path, "r") as f:
        names = sorted(f["frames"].keys(), key=int)
        out = []
        for name in names:
            attrs = f["frames"][name].attrs
            stage = attrs.get("stage", "")
            out.append((float(attrs.get("time", math.nan)),
                        stage.decode() if isinstance(stage, bytes) else str(stage)))
    return out


EARLY_FRACTION = 0.1     # Fig. 3's early frame: this far from the shear's start to its peak


def render_frames(stages: list[tuple[float, str]], peak_time: float) -> tuple[int, list[int]]:
    """Frames for Fig. 2 (last "prepare" frame, else 0) and Fig. 3 (early in the shear, and the
    shear frame closest in time to the peak; empty when there is no shear frame). "Early" is
    the first shear frame at least EARLY_FRACTION of the way from the start of the shear to
    the peak (to the last frame without a peak): on the rising branch, once the grains answer
    the ring, not the frames of the first steps, which show the bonded sample settling under
    its weight. It falls back to the first shear frame when that one would be the peak's."""
    prepare = [k for k, (_, stage) in enumerate(stages) if stage == "prepare"]
    shear = [k for k, (_, stage) in enumerate(stages) if stage == "shear"]
    sample_frame = prepare[-1] if prepare else 0
    if not shear:
        return sample_frame, []
    if math.isfinite(peak_time):
        at_peak = min(shear, key=lambda k: abs(stages[k][0] - peak_time))
    else:
        at_peak = shear[-1]
    t0 = stages[shear[0]][0]
    t_ref = stages[at_peak][0] if math.isfinite(peak_time) else stages[shear[-1]][0]
    early = [k for k in shear if stages[k][0] >= t0 + EARLY_FRACTION * (t_ref - t0)]
    start = early[0] if early and early[0] != at_peak else shear[0]
    return sample_frame, [start, at_peak]


def _render_figures(samples: list[SampleCurves], out_dir: Path, written: list,
                    velocity: str = "mean") -> None:
    sample = next((s for s in samples if (s.directory / STATES_NAME).is_file()), None)
    if sample is None:
        warnings.warn(f"fig2_sample.png and fig3_velocity.png skipped: no sample has a "
                      f"{STATES_NAME}", FigureWarning, stacklevel=3)
        return
    states = sample.directory / STATES_NAME
    try:
        stages = _frame_stages(states)
        if not stages:
            raise ValueError(f"{states}: no frames")
        from . import backend, render
        if not backend.initialized():
            backend.init(arch="cpu", precision="f64")
    except Exception as exc:  # noqa: BLE001 - a failed render must not stop the plots
        warnings.warn(f"fig2/fig3 skipped: {type(exc).__name__}: {exc}", FigureWarning,
                      stacklevel=3)
        return
    sample_frame, velocity_frames = render_frames(stages, sample.peak_time)
    jobs = [("fig2_sample.png", lambda out: render.figure_sample(states, out,
                                                                 frame=sample_frame))]
    if velocity_frames:
        jobs.append(("fig3_velocity.png",
                     lambda out: render.figure_velocity(states, out, frames=velocity_frames,
                                                        velocity=velocity)))
    else:
        warnings.warn(f"fig3_velocity.png skipped: {states} has no 'shear' frame",
                      FigureWarning, stacklevel=3)
    for name, job in jobs:
        out = out_dir / name
        try:
            job(out)
        except Exception as exc:  # noqa: BLE001
            warnings.warn(f"{name} skipped: {type(exc).__name__}: {exc}", FigureWarning,
                          stacklevel=3)
            continue
        written.append(out)


def refuse_file(out_dir: Path) -> None:
    """A ValueError naming `out_dir` (`--out`) when it exists and is not a directory, before
    any run is read (the outputs go into a folder)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--out {out_dir}: exists and is not a directory (the outputs go into "
                         "a folder)")


#: what `make_figures` may write into its folder (STUDY_SUMMARY_NAME too, for several runs)
FIGURE_FILES = ("fig4_stress_displacement.png", "fig4_stress_displacement.pdf", "table2.md",
                "table2.csv", "table2.png", "bonds_broken.png", "fig2_sample.png",
                "fig3_velocity.png")


def refuse_outputs(out_dir: Path, names) -> None:
    """A ValueError, before anything is read or written, when one of the files `names` of the
    folder `out_dir` cannot be replaced: a directory (or other non-file) of that name, or a
    folder the user cannot write into. Each file is replaced atomically, so without this a
    refusal met halfway would leave the folder with some files new and others old."""
    if out_dir.is_dir() and not os.access(out_dir, os.W_OK | os.X_OK):
        raise ValueError(f"--out {out_dir}: the folder is not writable: nothing written")
    for name in names:
        path = out_dir / name
        if (path.exists() or path.is_symlink()) and not path.is_file():
            raise ValueError(f"{path}: exists and is not a file (a directory?): nothing "
                             "written; remove it or choose another --out")


def make_folder(out_dir: Path) -> None:
    """Create the output folder `out_dir` (and its parents); a failure is a ValueError naming
    it (`--out`)."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--out {out_dir}: cannot create the folder: "
                         f"{exc.strerror or exc}") from None


def make_figures(run_dir, out_dir=None, *, render: bool = True,
                 velocity: str = "mean") -> list[Path]:
    """Write Fig. 4 (png, pdf), Table 2 (md, csv, png), bonds_broken.png and, with `render`,
    Fig. 2 and Fig. 3 of the run in `run_dir` into `out_dir` (default run_dir/figures).
    `velocity`: what Fig. 3 shows, "mean" (the paper's average velocity of the grains, over the
    interval between two snapshots) or "instant" (`tcd.render.figure_velocity`).

    `run_dir` may be a list of run directories of one study (split with ``tcd run --seeds``):
    their samples are shown together, `out_dir` must then be given, and the merged summary is
    written there too (:data:`STUDY_SUMMARY_NAME`). Returns the files written. Skipped
    samples and figures give a :class:`FigureWarning`.
    """
    from .render import VELOCITY_KINDS
    if velocity not in VELOCITY_KINDS:
        raise ValueError(f"velocity {velocity!r}: expected one of {', '.join(VELOCITY_KINDS)}")
    run_dirs = _as_run_dirs(run_dir)
    several = len(run_dirs) > 1
    if several and out_dir is None:
        raise ValueError("several run directories: give the folder for their figures (--out)")
    out_dir = Path(out_dir) if out_dir is not None else run_dirs[0] / "figures"
    refuse_file(out_dir)
    refuse_outputs(out_dir, FIGURE_FILES + ((STUDY_SUMMARY_NAME,) if several else ()))
    skipped: list = []
    summary, samples = load_runs(run_dirs, skipped)
    run_dir = run_dirs[0]
    make_folder(out_dir)
    written: list[Path] = []

    paper_test = is_paper_test(summary, samples)
    figure_stress_displacement(samples, out_dir / "fig4_stress_displacement.png", written,
                               paper_test=paper_test)
    if summary is None:
        state = "unreadable" if (run_dir / SUMMARY_NAME).exists() else "missing"
        warnings.warn(f"{run_dir / SUMMARY_NAME} {state}: Table 2 from the series peaks",
                      FigureWarning, stacklevel=2)
    if several:
        io.write_json(out_dir / STUDY_SUMMARY_NAME, summary)
        written.append(out_dir / STUDY_SUMMARY_NAME)
    rows = table2_rows(summary if summary is not None else summary_from_samples(samples),
                       paper_test)
    note = "" if paper_test else not_compared_note(summary)
    footnote = " ".join(t for t in (peak_at_end_note(samples),
                                    left_out_note(skipped, len(samples))) if t)
    _write_text(out_dir / "table2.md", table2_markdown(rows, note, footnote), written)
    _write_text(out_dir / "table2.csv", table2_csv(rows), written)
    figure_table2(rows, out_dir / "table2.png", written, note, footnote)
    figure_bonds_broken(samples, summary, out_dir / "bonds_broken.png", written)
    if render:
        _render_figures(samples, out_dir, written, velocity)
    return written


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tcd.figures", description=__doc__.split(
        "\n")[0])
    parser.add_argument("run_dir", nargs="+",
                        help="run directory (summary.json, sample_<seed>/...); several: the "
                             "parts of one study split with tcd run --seeds")
    parser.add_argument("--out", default=None, help="output folder (default RUN_DIR/figures; "
                        "needed with several run directories)")
    parser.add_argument("--no-render", action="store_true", help="skip Fig. 2 and Fig. 3")
    parser.add_argument("--velocity", choices=("mean", "instant"), default="mean",
                        help="Fig. 3: each grain's mean velocity between two snapshots (the "
                             "paper's average velocity; default) or the snapshot's own")
    args = parser.parse_args(argv)
    if len(args.run_dir) > 1 and args.out is None:
        parser.error("several run directories: give --out")
    for path in make_figures(args.run_dir, args.out, render=not args.no_render,
                             velocity=args.velocity):
        print(os.fspath(path))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
