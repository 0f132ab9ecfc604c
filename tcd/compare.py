"""Several runs side by side (`tcd compare`): a parameter study's shear curves and peaks.

`tcd figures` draws one study (one scenario, its samples); `tcd compare RUN_A RUN_B ... --out
DIR` puts runs of different scenarios together, as a calibration or sensitivity study does
(a yield stress, a ring friction, a time step varied): one colour per run, each sample's
smoothed curve thin and the run's mean curve thick, each run's mean peak with its spread, and
a table of the runs with the scenario settings in which they differ.

Outputs: `compare.png` and `compare.pdf` (shear stress against displacement), `compare.md`
and `compare.csv` (one row per run). Nothing is recomputed by a simulation: the curves and
peaks are those of each sample's `shear_series.h5`, smoothed and read as `tcd figures` reads
them (`tcd.figures.load_run`), so a run's numbers here are its Table 2's.
"""
from __future__ import annotations

import csv
import io as _stdio
import math
import os
import textwrap
import warnings
from pathlib import Path

import numpy as np

from . import figures, io
from .config import flat_keys

#: scenario keys that never make two runs differ in physics (names, seeds, outputs)
IGNORED_KEYS = figures.STUDY_FREE_KEYS


def differing_settings(scenarios: list[dict | None]) -> list[str]:
    """The dotted scenario keys whose values are not the same in every run (a run whose
    scenario.toml is missing is left out), in the scenarios' order."""
    flats = [flat_keys(s) for s in scenarios if s is not None]
    keys = list(dict.fromkeys(k for f in flats for k in f))
    missing = object()
    return [k for k in keys if len({repr(f.get(k, missing)) for f in flats}) > 1]


def _short(text: str, width: int = 28) -> str:
    """`text`, or its last `width` - 1 characters after an ellipsis (a path's tail tells most)."""
    return text if len(text) <= width else "…" + text[-(width - 1):]


def _shown(value) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_shown(v) for v in value) + "]"
    return str(value)


def counted(samples: list) -> list:
    """The samples a run's means are taken over: its finished ones when it has any (a shear
    stopped early would pull a mean peak down to where it stopped), else its stopped ones,
    whose numbers are then so far."""
    finished = [s for s in samples if not s.stopped]
    return finished or list(samples)


def run_numbers(samples: list) -> dict:
    """Mean and population std over a run's samples (SampleCurves; the finished ones when
    there are any, :func:`counted`) of the peak (MPa, mm), the stress at the end of the test
    (MPa) and the share of bonds broken by then; `n_samples` the samples counted, `n_stopped`
    the stopped ones left out."""
    def stats(values):
        values = np.array([v for v in values if math.isfinite(v)], dtype=float)
        if not values.size:
            return math.nan, math.nan
        return float(values.mean()), float(values.std()) if values.size > 1 else math.nan

    def broken_share(s):
        # the initial bonds as Fig. 4's companion counts them (intact + broken at the start)
        ser, total = s.series, figures._bonds_total(s, None)
        ends = [ser[k][-1] for k in ("bonds_broken_tension", "bonds_broken_shear")
                if k in ser and len(ser[k])]
        return float(sum(ends)) / total if len(ends) == 2 and total > 0 else math.nan

    used = counted(samples)
    out = {"n_samples": len(used), "n_stopped": len(samples) - len(used)}
    samples = used
    for key, std_key, values in (
            ("tau_peak_MPa", "tau_peak_std", [s.tau_peak * 1e-6 for s in samples]),
            ("d_peak_mm", "d_peak_std", [s.d_peak * 1e3 for s in samples]),
            ("tau_end_MPa", "tau_end_std", [float(s.smoothed[-1]) * 1e-6 if s.smoothed.size
                                            else math.nan for s in samples]),
            ("bonds_broken_share", "bonds_broken_std", [broken_share(s) for s in samples])):
        out[key], out[std_key] = stats(values)
    return out


def sample_files(summary: dict | None) -> dict:
    """{seed: {stage key: SHA-256}} of the files a run's samples sheared, as its summary
    recorded them (`inputs`, since session 57; a shear from `sample = ...`)."""
    out = {}
    for smp in (summary or {}).get("samples") or []:
        if isinstance(smp, dict) and isinstance(smp.get("inputs"), dict):
            out[str(smp.get("seed"))] = {k: v.get("sha256") for k, v in smp["inputs"].items()
                                         if isinstance(v, dict) and v.get("sha256")}
    return out


def sample_files_note(runs: list[dict]) -> str:
    """The sentence saying whether the runs sheared the same sample files, seed by seed (by
    the SHA-256 their summaries recorded), whatever the paths were spelled as; "" when fewer
    than two runs recorded them for a common seed. Two runs of one sample path may have
    sheared two different files (a sample made again), and two paths may name one file."""
    recorded = []
    for r in runs:                      # the samples compared (--seeds) that recorded theirs
        shown = {str(s.seed) for s in r["samples"]}
        files = {seed: f for seed, f in sample_files(r["summary"]).items() if seed in shown}
        if files:
            recorded.append((r["label"], files))
    if len(recorded) < 2:
        return ""
    same, differ = [], []
    for seed in sorted(set.intersection(*(set(f) for _, f in recorded)), key=figures._seed_key):
        for stage in sorted(set.intersection(*(set(f[seed]) for _, f in recorded))):
            digests = {f[seed][stage] for _, f in recorded}
            (same if len(digests) == 1 else differ).append(f"{seed} ({stage})")
    if not same and not differ:
        return ""
    labels = ", ".join(label for label, _ in recorded)
    text = f"Sample files sheared, by the SHA-256 each run recorded ({labels}): "
    parts = []
    if same:
        parts.append("the same files for seeds " + ", ".join(same))
    if differ:
        parts.append("**different files** for seeds " + ", ".join(differ))
    return text + "; ".join(parts) + "."


def mean_curve(samples: list, points: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """(displacement m, mean smoothed stress Pa) of a run's samples (the finished ones when
    there are any, :func:`counted`), on a common grid up to the shortest one's end."""
    samples = counted(samples)
    ends = [float(np.nanmax(s.displacement)) for s in samples if s.displacement.size]
    if not ends:
        return np.zeros(0), np.zeros(0)
    grid = np.linspace(0.0, min(ends), points)
    curves = [np.interp(grid, s.displacement, s.smoothed) for s in samples if s.displacement.size]
    return grid, np.mean(curves, axis=0)


#: what `compare_runs` writes into its folder
COMPARE_FILES = ("compare.png", "compare.pdf", "compare.md", "compare.csv")


def compare_runs(run_dirs, out_dir, labels=None, seeds=None, target_peak=None,
                 setting=None, report=None) -> list[Path]:
    """Write compare.png/.pdf/.md/.csv of `run_dirs` (at least two run directories) into
    `out_dir`; `labels`: one name per run (default: each directory's name); `seeds`: only
    these samples of each run (the same samples under two settings; default: all).
    `target_peak` (MPa): also find the value of the numeric setting in which the runs differ
    (`setting`, a dotted key, when they differ in several) at which the mean peak would be
    that stress (:func:`calibrate`), written to compare.md and appended to the list `report`
    when one is given. Returns the files written. Raises ValueError for fewer than two runs,
    labels that do not match them, a run without a usable sample (or without any of `seeds`),
    a target with no setting to fit; FileNotFoundError for a missing directory."""
    run_dirs = [Path(p) for p in run_dirs]
    if len(run_dirs) < 2:
        raise ValueError("tcd compare needs at least two run directories (one run's figures: "
                         "tcd figures RUN_DIR)")
    given = labels is not None
    if labels is None:
        labels = [p.name or os.fspath(p) for p in run_dirs]
    labels = [str(x).strip() for x in labels]
    if len(labels) != len(run_dirs):
        raise ValueError(f"{len(labels)} labels for {len(run_dirs)} run directories: give one "
                         "label per run")
    for label in labels:
        if not label or any(c in label for c in "|\n\r"):
            raise ValueError(f"label {label!r}: a label must be a non-empty name without '|' "
                             "or line breaks (it heads a column of compare.md)")
    if len(set(labels)) != len(labels):
        raise ValueError(f"labels {labels} repeat a name" + (
            "" if given else " (two run folders of one name: give --labels)"))
    for run_dir in run_dirs:
        if not run_dir.is_dir():
            raise FileNotFoundError(f"{run_dir}: run directory not found")
    out_dir = Path(out_dir)
    figures.refuse_file(out_dir)
    figures.refuse_outputs(out_dir, COMPARE_FILES)
    seeds = None if seeds is None else list(dict.fromkeys(seeds))      # 1,1: seed 1
    wanted = None if seeds is None else {str(x) for x in seeds}
    runs = []
    for label, run_dir in zip(labels, run_dirs):
        summary, samples = figures.load_run(run_dir, stopped=True)
        if wanted is not None:
            have = sorted((str(s.seed) for s in samples), key=figures._seed_key)
            samples = [s for s in samples if str(s.seed) in wanted]
            if not samples:
                asked = ", ".join(sorted(wanted, key=figures._seed_key))
                raise ValueError(f"{run_dir}: none of the seeds {asked} (its samples: "
                                 f"{', '.join(have)})")
        runs.append({"label": label, "dir": run_dir, "summary": summary, "samples": samples,
                     **run_numbers(samples)})
    for r, scenario in zip(runs, figures.scenarios_of([r["dir"] for r in runs])):
        r["scenario"] = scenario
        if scenario is None:
            warnings.warn(f"{Path(r['dir']) / 'scenario.toml'} missing or unreadable, and no "
                          "sample of the run records its scenario: its settings are shown as "
                          "'?' and not compared", figures.FigureWarning, stacklevel=2)
    keys = differing_settings([r["scenario"] for r in runs])
    for r in runs:
        flat = flat_keys(r["scenario"]) if r["scenario"] is not None else {}
        r["settings"] = {k: _shown(flat.get(k)) if r["scenario"] is not None else "?"
                         for k in keys}
    fit = calibrate(runs, keys, target_peak, setting) if target_peak is not None else None
    figures.make_folder(out_dir)
    written: list[Path] = []
    _figure(runs, keys, out_dir / "compare.png", written, fit=fit)
    text = table_markdown(runs, keys, seeds)
    if fit is not None:
        text += "\n" + fit["text"] + "\n"
        if report is not None:
            report.append(fit["text"])
    figures._write_text(out_dir / "compare.md", text, written)
    figures._write_text(out_dir / "compare.csv", table_csv(runs, keys), written)
    return written


def calibrate(runs: list[dict], keys: list[str], target: float, setting: str | None = None) -> dict:
    """The value of a numeric scenario setting at which the runs' mean peak (MPa, as in
    compare.md) would be `target` MPa: linear interpolation between the runs whose peaks
    bracket it, taken in the order of the setting (every crossing when the peaks are not
    monotonic), with the peak's displacement interpolated the same way; where no two runs
    bracket it, the least-squares line through all of them, said to be an extrapolation.
    `setting`: the dotted key to fit (default: the one numeric key among `keys`, the settings
    in which the runs differ). Returns {"setting", "values": [crossings], "slope" (MPa per
    unit of the setting, least squares), "extrapolated", "target", "text" (a paragraph with the
    caveats: peaks so far, curves still rising, means over different samples, other settings
    that differ)}. Raises ValueError when there is no such setting or too few runs carry it."""
    if not (isinstance(target, (int, float)) and math.isfinite(target) and target > 0):
        raise ValueError(f"--target-peak {target}: expected a positive stress in MPa")

    unknown = [f"{r['label']} ({r['dir']})" for r in runs if r["scenario"] is None]
    if unknown:
        raise ValueError(f"--target-peak: the scenario of {', '.join(unknown)} is not known "
                         "(its scenario.toml missing or unreadable, and no sample records it): "
                         "its settings cannot be fitted; restore its scenario.toml")
    flats = {r["label"]: flat_keys(r["scenario"]) for r in runs}

    def number(r, key):
        value = flats[r["label"]].get(key)
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        return float(value) if ok and math.isfinite(value) else None

    if setting is None:
        numeric = [k for k in keys if all(number(r, k) is not None for r in runs)]
        if len(numeric) != 1:
            raise ValueError(
                "--target-peak: the runs differ in no numeric setting to fit" if not numeric else
                f"--target-peak: the runs differ in {len(numeric)} numeric settings "
                f"({', '.join(numeric)}): name the one to fit with --fit-setting")
        setting = numeric[0]
    elif setting not in keys:
        raise ValueError(f"--fit-setting {setting}: the runs do not differ in it (they differ "
                         f"in: {', '.join(keys) or 'nothing'})")
    missing = [r["label"] for r in runs if number(r, setting) is None]
    if missing:
        raise ValueError(f"--fit-setting {setting}: not a number in the scenario of "
                         f"{', '.join(missing)}")
    points = sorted(((number(r, setting), r["tau_peak_MPa"], r["d_peak_mm"], r["label"])
                     for r in runs if math.isfinite(r["tau_peak_MPa"])), key=lambda p: p[0])
    xs = np.array([p[0] for p in points])
    if len(set(xs.tolist())) < 2:
        raise ValueError(f"--target-peak: fewer than two values of {setting} with a peak")
    ys = np.array([p[1] for p in points])
    slope, intercept = np.polyfit(xs, ys, 1)
    values = []
    for (x0, y0, d0, _), (x1, y1, d1, _) in zip(points, points[1:]):
        if y0 != y1 and (y0 - target) * (y1 - target) <= 0 and x0 != x1:
            f = (target - y0) / (y1 - y0)
            value = (x0 + f * (x1 - x0), d0 + f * (d1 - d0))
            if not values or not math.isclose(values[-1][0], value[0]):
                values.append(value)
    extrapolated = not values and slope != 0
    if extrapolated:
        values = [((target - intercept) / slope, math.nan)]
    peaks = ", ".join(f"{y:.4g} MPa at {x:g} ({label})" for x, y, _, label in points)
    text = [f"Calibration (`--target-peak {target:g}`): the runs' mean peaks against "
            f"{setting}: {peaks}; least-squares slope {slope:.4g} MPa per unit of {setting}. "]
    if not values:
        text.append(f"The peaks do not change with {setting}: no value reaches {target:g} MPa.")
    elif extrapolated:
        text.append(f"No two runs bracket {target:g} MPa: the least-squares line reaches it at "
                    f"{setting} = **{values[0][0]:.4g}**, an extrapolation; run that value to "
                    "check it.")
    else:
        text.append(f"{'Each value' if len(values) > 1 else 'The value'} of {setting} at which "
                    f"the mean peak would be {target:g} MPa, interpolated linearly between the "
                    "two runs that bracket it: " + "; ".join(
                        f"**{x:.4g}**" + (f" (the peak at {d:.3g} mm)" if math.isfinite(d) else "")
                        for x, d in values) + "."
                    + (" The peaks are not monotonic in the setting: several crossings."
                       if len(values) > 1 else ""))
    caveats = []
    so_far = [r["label"] for r in runs if r["samples"] and all(s.stopped for s in counted(r["samples"]))]
    if so_far:
        caveats.append(f"the peaks of {', '.join(so_far)} are so far (stopped shears): a higher "
                       "one may come")
    rising = [r["label"] for r in runs
              if any(s.peak_at_end and not s.stopped for s in counted(r["samples"]))]
    if rising:
        caveats.append(f"some curves of {', '.join(rising)} still rise at their end: those "
                       "peaks are lower bounds")
    sets = {tuple(sorted((str(s.seed) for s in counted(r["samples"])), key=figures._seed_key))
            for r in runs}
    if len(sets) > 1:
        caveats.append("the runs' means are over different samples (`--seeds` takes the same "
                       "ones)")
    others = [k for k in keys if k != setting]
    if others:
        caveats.append(f"the runs also differ in {', '.join(others)}, which the fit ignores")
    if caveats:
        text.append(" Caveats: " + "; ".join(caveats) + ".")
    return {"setting": setting, "target": target, "values": [x for x, _ in values],
            "slope": float(slope), "extrapolated": extrapolated, "text": "".join(text)}


def table_markdown(runs: list[dict], keys: list[str], seeds=None) -> str:
    head = ["run", *keys, "samples", "peak τ (MPa)", "at d (mm)", "τ at the end (MPa)",
            "bonds broken", "folder"]
    unfinished = [r["label"] for r in runs if r["summary"] is None]
    lines = ["Runs compared: each run's mean ± population std over its samples (peak of the "
             "smoothed curve, as its Table 2; over its finished samples when some stopped "
             "early), and the scenario settings in which the runs differ.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in runs:
        share = r["bonds_broken_share"]
        so_far = any(smp.stopped for smp in counted(r["samples"]))
        lines.append("| " + " | ".join([
            r["label"], *(r["settings"][k] for k in keys),
            str(r["n_samples"]) + (f" (and {r['n_stopped']} stopped, not counted)"
                                   if r["n_stopped"] else ""),
            figures._fmt(r["tau_peak_MPa"], 3, r["tau_peak_std"]),
            figures._fmt(r["d_peak_mm"], 2, r["d_peak_std"]),
            figures._fmt(r["tau_end_MPa"], 3, r["tau_end_std"])
            + (" (stopped before the end)" if so_far else ""),
            f"{100 * share:.1f} %" if math.isfinite(share) else "–",
            os.fspath(r["dir"])]) + " |")
    unknown = [r["label"] for r in runs if r.get("scenario", {}) is None]
    if unknown:
        lines += ["", f"The scenario of {', '.join(unknown)} is not known (its scenario.toml "
                      "missing or unreadable): its settings are not compared."]
    elif not keys:
        lines += ["", "The runs' scenarios do not differ (seeds, names and outputs aside)."]
    if seeds is not None:
        taken = "; ".join(f"{r['label']} ({', '.join(str(s.seed) for s in r['samples'])})"
                          for r in runs)
        lines += ["", f"Only the samples of seeds {', '.join(map(str, seeds))} (`--seeds`), by "
                      f"run: {taken}."]
    went_on = []
    for r in runs:
        records = [(smp.get("seed", "?"), smp["branched_from"][-1])
                   for smp in (r["summary"] or {}).get("samples", []) or []
                   if isinstance(smp, dict) and isinstance(smp.get("branched_from"), list)
                   and smp["branched_from"]]
        records += [(s.seed, s.branched_from) for s in r["samples"] if s.stopped]
        for seed, record in records:
            try:
                went_on.append(f"{r['label']} (seed {seed}) " + io.branch_origin(record))
            except (KeyError, IndexError, TypeError, ValueError):
                continue
    stopped = [f"{r['label']} ({', '.join(where)})" for r in runs
               for where in [[f"seed {s.seed} at {float(s.displacement.max()) * 1e3:.3f} mm"
                              for s in r["samples"] if s.stopped]] if where]
    # (a stopped shear's curve ends where it stopped: listed below, not here)
    ends = [(r["label"], [str(s.seed) for s in r["samples"] if s.peak_at_end and not s.stopped])
            for r in runs]
    rising = [f"{label} ({', '.join(seeds_)})" for label, seeds_ in ends if seeds_]
    if rising:
        lines += ["", "Curves still rising at their end (the peak within half a smoothing window "
                      "of the last point: no failure seen, the peak a lower bound), by run "
                      "(seeds): " + "; ".join(rising) + "."]
    if stopped:
        lines += ["", "Shears stopped before the end of their test (no series file: their curves "
                      "and peaks so far, from the checkpoint a `--resume` continues from; a "
                      "higher peak may come later; a run's means leave them out when it has "
                      "finished samples), by run: " + "; ".join(stopped) + "."]
    files = sample_files_note(runs)
    if files:
        lines += ["", files]
    if went_on:
        lines += ["", "Runs that went on from another run's state (`tcd run --from`; up to "
                      "there their curves are that run's): " + "; ".join(went_on) + "."]
    if unfinished:
        lines += ["", f"No summary.json in {', '.join(unfinished)}: unfinished (or stopped) "
                      "runs, their curves as far as their series go."]
    return "\n".join(lines) + "\n"


def table_csv(runs: list[dict], keys: list[str]) -> str:
    buffer = _stdio.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    numbers = ["n_samples", "tau_peak_MPa", "tau_peak_std", "d_peak_mm", "d_peak_std",
               "tau_end_MPa", "tau_end_std", "bonds_broken_share", "bonds_broken_std",
               "n_stopped"]
    writer.writerow(["label", *keys, *numbers, "folder"])
    for r in runs:
        writer.writerow([r["label"], *(r["settings"][k] for k in keys),
                         *("" if isinstance(r[k], float) and math.isnan(r[k])
                           else (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k])
                           for k in numbers), os.fspath(r["dir"])])
    return buffer.getvalue()


def _figure(runs: list[dict], keys: list[str], out_png: Path, written: list,
            fit=None) -> None:
    import matplotlib
    with matplotlib.rc_context(figures._RC):
        fig = figures._new_figure(7.2, 4.2 + 0.22 * len(runs))
        ax = fig.add_subplot()
        for r, color in zip(runs, figures._colors(len(runs))):
            def left_out(s):               # a stopped one left out of the mean: dashed
                return s.stopped and r["n_stopped"] > 0

            for s in r["samples"]:
                ax.plot(s.displacement * 1e3, s.smoothed * 1e-6, color=color, lw=0.6,
                        alpha=0.35, zorder=1, ls="--" if left_out(s) else "-")
            d, tau = mean_curve(r["samples"])
            shown = "; ".join(f"{k.split('.')[-1]} {_short(r['settings'][k])}" for k in keys[:3])
            at = [f"{float(s.displacement.max()) * 1e3:.2f}" for s in r["samples"] if s.stopped]
            ends = [f"{len(at)} stopped at {', '.join(at)} mm" + (
                ", dashed, not in the mean" if r["n_stopped"] else "")] if at else []
            label = (f"{r['label']} ({r['n_samples']} sample{'s' if r['n_samples'] != 1 else ''}"
                     f"{': ' + shown if shown else ''}{'; ' + ', '.join(ends) if ends else ''})")
            # a long label (a file path, many settings) would squeeze the axes to nothing
            ax.plot(d * 1e3, tau * 1e-6, color=color, lw=2.0, zorder=2,
                    label="\n".join(textwrap.wrap(label, 80)))
            xerr = r["d_peak_std"] if math.isfinite(r["d_peak_std"]) else None
            yerr = r["tau_peak_std"] if math.isfinite(r["tau_peak_std"]) else None
            ax.errorbar(r["d_peak_mm"], r["tau_peak_MPa"], xerr=xerr, yerr=yerr, fmt="o",
                        ms=6, mfc="white", mec=color, mew=1.6, ecolor=color, capsize=3, zorder=4)
        ax.plot([], [], "o", ms=6, mfc="white", mec="0.3", mew=1.6,
                label="mean peak ± std of each run")
        if fit is not None:
            found = ", ".join(f"{x:.4g}" for x in fit["values"]) or "none"
            ax.axhline(fit["target"], color="0.3", lw=0.9, ls=":", zorder=0,
                       label=f"target peak {fit['target']:g} MPa: {fit['setting']} = {found}"
                             + (" (extrapolated)" if fit["extrapolated"] else ""))
        ax.set_xlim(left=0.0)
        ax.set_xlabel("Imposed displacement d (mm)")
        ax.set_ylabel("Shear stress τ (MPa)")
        ax.grid(True, lw=0.4, alpha=0.4)
        ax.tick_params(direction="in", top=True, right=True)
        ax.legend(loc="upper left", bbox_to_anchor=(0.0, -0.14), frameon=False,
                  title="mean of each run's smoothed curves (each sample faint)",
                  title_fontsize=8.5, alignment="left")
        figures._save(fig, out_png, written)
        figures._save(fig, out_png.with_suffix(".pdf"), written)


__all__ = ["calibrate", "compare_runs", "counted", "differing_settings", "mean_curve", "run_numbers",
           "sample_files", "sample_files_note"]
