"""The `tcd` command: run scenarios, inspect, render and plot their files, benchmark.

Each subcommand's handler imports what it needs when it runs, so `tcd --help` stays instant.
Errors a user can fix (a bad scenario, a missing file, results that would be overwritten) print
one `tcd: error: ...` message and exit with status 2 before any simulation starts; an interrupt
exits with 130 and, for `tcd run`, says how to resume.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import shlex
import sys
from pathlib import Path

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_IO = 74            # sysexits' EX_IOERR: the file system refused a read or a write
ARCHS = ("cpu", "gpu")
PRECISIONS = ("f64", "f32")
COLOR_MODES = ("layer", "speed", "vx", "bond-damage")      # = tcd.render.COLOR_MODES
CAMERAS = ("iso", "front", "perspective")                  # = tcd.render.CAMERA_PRESETS
SECTIONS = ("xz", "yz")
SUMMARY_FILE = "summary.json"


class UsageError(Exception):
    """A problem the user can fix; printed as `tcd: error: ...`, exit status 2."""


# --- helpers -------------------------------------------------------------------------------------
def _existing_file(path) -> Path:
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: no such file")
    if path.is_dir():
        raise UsageError(f"{path}: is a directory, expected a file")
    return path


@contextlib.contextmanager
def _reading(path: Path):
    """Errors met while reading `path` (and writing what is made of it) as one line that
    names the file at fault: h5py reports damaged files as OSError, RuntimeError or KeyError
    (a missing group); an OSError about another file is an output that cannot be written."""
    try:
        yield
    except BrokenPipeError:
        raise                                   # `tcd info FILE | head`: main's business
    except OSError as exc:
        other = getattr(exc, "filename", None)
        if other is not None and os.path.abspath(os.fspath(other)) != os.path.abspath(path):
            raise UsageError(f"{other}: cannot write: {exc.strerror or exc}") from None
        raise UsageError(f"{path}: cannot read: {exc}") from None
    except (RuntimeError, KeyError) as exc:
        raise UsageError(f"{path}: cannot read ({type(exc).__name__}: {exc}); the file is "
                         "damaged or is not a complete tcd file") from None


@contextlib.contextmanager
def _writing():
    """The file system's refusal (`tcd figures`, `tcd compare`: an output that cannot be
    written) as one line that names the file, with status 2 as the other commands that make
    files from a run's (docs/usage.md)."""
    try:
        yield
    except BrokenPipeError:
        raise
    except OSError as exc:
        raise UsageError(_os_message(exc)) from None


def _existing_results(out_dir: Path) -> list[Path]:
    """Files in `out_dir` that a fresh run would overwrite: a summary, checkpoints, HDF5 data."""
    if not out_dir.is_dir():
        return []
    found = []
    for path in sorted(out_dir.rglob("*")):
        if path.is_file() and (path.name == SUMMARY_FILE or "checkpoint" in path.name
                               or path.suffix == ".h5"):
            found.append(path)
    return found


def _is_records(value) -> bool:
    """A non-empty list of dicts (a run's samples, a benchmark's phases, a phase's walls)."""
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _flatten(data, prefix: str = "") -> list[tuple[str, object]]:
    rows = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            rows += _flatten(value, f"{name}.")
        elif _is_records(value):
            for k, item in enumerate(value):      # one row per flat item (e.g. the benchmarks' phases)
                if any(isinstance(b, dict) or _is_records(b) for b in item.values()):
                    rows += _flatten(item, f"{name}[{k}].")   # nested (e.g. a run's samples)
                else:
                    rows.append((f"{name}[{k}]", "; ".join(f"{a}={_cell(b)}" for a, b in item.items())))
        else:
            rows.append((name, value))
    return rows


def _cell(value) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else str(value)
    if isinstance(value, (list, tuple)):
        if len(value) <= 8 and all(not isinstance(v, (list, tuple, dict)) for v in value):
            return ", ".join(_cell(v) for v in value)
        return f"[{len(value)} items]"
    return str(value)


def format_table(data: dict) -> str:
    """A dict (nested dicts flattened to dotted keys) as two aligned columns."""
    rows = [(k, _cell(v)) for k, v in _flatten(data)]
    if not rows:
        return "(empty)"
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def _json_default(obj):
    if hasattr(obj, "tolist"):          # NumPy scalars and arrays
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def _print_result(result: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(result, indent=2, default=_json_default))
    else:
        print(format_table(result))


# --- handlers ------------------------------------------------------------------------------------
def _resume_command(args) -> str:
    words = ["tcd", "run", args.scenario, "--out", str(args.out_dir)]
    if args.arch:
        words += ["--arch", args.arch]
    if args.precision:
        words += ["--precision", args.precision]
    if getattr(args, "seeds", None):
        words += ["--seeds", ",".join(map(str, args.seeds))]
    for text in getattr(args, "set", None) or []:
        words += ["--set", text]
    if getattr(args, "jobs", 1) > 1:
        words += ["--jobs", str(args.jobs)]
    if getattr(args, "batch", False):
        words += ["--batch"]
    return shlex.join(words + ["--resume"])


def cmd_run(args) -> int:
    from .config import load_scenario, parse_setting
    settings = [parse_setting(text) for text in getattr(args, "set", None) or []]
    scenario = load_scenario(args.scenario, settings, seeds=args.seeds).with_overrides(
        arch=args.arch, precision=args.precision)
    scenario = scenario.with_seeds(args.seeds)
    for key, reason in scenario.doubts():       # values likely in another unit: run as written
        print(f"tcd: warning: {scenario.source}: {key}: {reason}", file=sys.stderr)
    out_dir = Path(args.out) if args.out else Path("runs") / scenario.name
    args.out_dir = out_dir
    source = getattr(args, "from_run", None)
    if source and (args.resume or args.batch):
        raise UsageError("--from starts a new run from another run's checkpoints: it takes no "
                         "--resume (resume the new run itself with --resume) and no --batch")
    if args.resume:
        if out_dir.exists() and not out_dir.is_dir():
            raise UsageError(f"nothing to resume: {out_dir} is a file, not a run directory")
        if not out_dir.is_dir():
            raise UsageError(f"nothing to resume: {out_dir} does not exist "
                             f"(run without --resume to start)")
    elif not source:        # (--from checks that its --out is new: tcd.branch)
        existing = _existing_results(out_dir)
        if existing:
            shown = ", ".join(str(p) for p in existing[:3])
            more = f" and {len(existing) - 3} more" if len(existing) > 3 else ""
            resumable = any(p.name == SUMMARY_FILE or "checkpoint" in p.name for p in existing)
            advice = ("continue it with --resume or choose another --out directory" if resumable
                      else "it has no checkpoint to resume from: remove it or choose another "
                           "--out directory")
            raise UsageError(f"{out_dir} already holds results ({shown}{more}); {advice}")
    if args.batch:
        from .runner import batch_problem, run_batch
        if args.jobs > 1:
            raise UsageError("--batch runs every sample in one simulation: it takes no --jobs")
        problem = batch_problem(scenario)
        if problem:
            raise UsageError(problem)
        summary = run_batch(scenario, out_dir, resume=args.resume, progress=True)
    else:
        from .runner import run_scenario
        resume = args.resume
        if source:
            from .branch import branch_run
            from .runner import check_run_settings
            check_run_settings(scenario, args.jobs, scenario.seeds)
            print(f"tcd: {scenario.name}: going on from {source} in {out_dir}:\n"
                  + branch_run(scenario, source, out_dir), file=sys.stderr)
            resume = True
        summary = run_scenario(scenario, out_dir, resume=resume, progress=True, jobs=args.jobs)
    print(f"tcd: {scenario.name}: results in {out_dir}")
    if summary:
        print(format_table(summary))
    return 0


def cmd_info(args) -> int:
    if Path(args.file).is_dir():            # a run directory: the state of its samples
        if args.set:
            raise UsageError("--set applies to a scenario file (tcd info SCENARIO.toml --set ...)")
        from .runner import run_info
        print(run_info(args.file))
        return 0
    if args.set and not args.file.endswith(".toml") and Path(args.file).is_file():
        raise UsageError(f"--set applies to a scenario file (tcd info SCENARIO.toml --set ...), "
                         f"not to {args.file}")
    if args.file.endswith(".toml") or args.set:   # a scenario: checked, not run
        from .config import describe, load_scenario, parse_setting
        scenario = load_scenario(args.file, [parse_setting(t) for t in args.set or []])
        if any(getattr(stage, "sample", "") for stage in scenario.stages):
            from .runner import check_samples       # (imports Taichi: only when needed)
            check_samples(scenario, scenario.seeds)     # each sample file read, as `tcd run` does
        print(describe(scenario))
        return 0
    path = _existing_file(args.file)
    from . import io
    with _reading(path):
        text = io.info(path)
    print(text)
    return 0


def _joined_frames(argv: list) -> list:
    """`--frames -1,-2` as `--frames=-1,-2`: argparse takes a value that starts with '-' and is
    not a plain negative number for an option, although negative frame indices count from the
    end."""
    out, k = [], 0
    while k < len(argv):
        if (argv[k] == "--frames" and k + 1 < len(argv) and isinstance(argv[k + 1], str)
                and re.fullmatch(r"-\d+(,\s*-?\d+)*,?", argv[k + 1])):
            out.append(f"--frames={argv[k + 1]}")
            k += 2
        else:
            out.append(argv[k])
            k += 1
    return out


def _frames(text):
    if text is None or text == "all":
        return text
    try:
        return list(dict.fromkeys(int(k) for k in text.split(",") if k.strip()))  # once each
    except ValueError:
        raise UsageError(f"--frames {text!r}: expected 'all' or comma-separated frame indices") \
            from None


def cmd_render(args) -> int:
    path = _existing_file(args.file)
    frames = _frames(args.frames)
    from .render import check_output
    check_output(args.out, args.frame)      # before Taichi starts (seconds)
    folder = Path(os.path.abspath(args.out)).parent
    if not folder.is_dir():                 # as export and analyse: no folder made by mistake
        what = "is a file, not a folder" if folder.exists() else "does not exist"
        raise UsageError(f"--out {args.out}: directory {folder} {what}")
    import tcd
    tcd.init(args.arch, args.precision)
    from .render import WriterMissing, render_file
    with _reading(path):
        try:
            render_file(path, args.out, frame=args.frame, frames=frames, color=args.color,
                        section=args.section, camera=args.camera, width=args.width,
                        height=args.height, fps=args.fps)
        except WriterMissing as exc:    # no MP4 writer installed; h5py's RuntimeError of a
            raise UsageError(str(exc)) from None        # damaged file: _reading names it
    print(f"wrote {args.out}")
    return 0


def cmd_export(args) -> int:
    path = _existing_file(args.file)
    frames = _frames(args.frames)
    parts = list(dict.fromkeys(q.strip() for q in args.parts.split(",") if q.strip()))
    from .export import export
    with _reading(path):
        written = export(path, args.out, frames="all" if frames is None else frames, parts=parts,
                         prefix=args.prefix)
    pvd = [str(w) for w in written if w.suffix == ".pvd"]
    print(f"wrote {len(written) - len(pvd)} VTK files into {args.out}; open in ParaView: "
          + ", ".join(pvd))
    new = {w.name for w in written}
    older = sorted(f.name for w in written if w.suffix == ".pvd"
                   for f in w.parent.glob(w.stem + "_*.vtu") if f.name not in new)
    if older:
        print(f"tcd: note: {len(older)} .vtu files of an earlier export are also in {args.out} "
              f"(e.g. {older[0]}); the .pvd files list this export's frames only",
              file=sys.stderr)
    return 0


def cmd_analyse(args) -> int:
    path = _existing_file(args.file)
    frames = _frames(args.frames)
    from .analysis import analyse
    with _reading(path):
        written = analyse(path, args.out, frames="all" if frames is None else frames,
                          time_step=args.time_step)
    print("wrote " + ", ".join(written))
    return 0


def _figure_warnings_as_lines(make):
    """`make()` with the figures' warnings printed as one line each (`tcd: warning: ...`), not
    with the source line that raised them; returns what `make` returns."""
    import warnings
    from . import figures
    category = getattr(figures, "FigureWarning", UserWarning)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", category)
        try:
            return make()
        finally:
            for w in caught:
                if issubclass(w.category, category):
                    print(f"tcd: warning: {w.message}", file=sys.stderr)
                else:
                    warnings.showwarning(w.message, w.category, w.filename, w.lineno)


def _run_dirs(paths) -> list[Path]:
    run_dirs = [Path(p) for p in paths]
    for run_dir in run_dirs:
        if not run_dir.is_dir():
            raise UsageError(f"{run_dir}: no such run directory")
    return run_dirs


def cmd_figures(args) -> int:
    run_dirs = _run_dirs(args.run_dir)
    if len(run_dirs) > 1 and args.out is None:
        raise UsageError("several run directories (the parts of one study): give --out DIR "
                         "for their figures")
    from . import figures
    with _writing():
        written = _figure_warnings_as_lines(lambda: figures.make_figures(
            run_dirs[0] if len(run_dirs) == 1 else run_dirs, args.out, velocity=args.velocity))
    for path in written:
        print(path)
    if not written:
        print(f"tcd: no figures written from {', '.join(map(str, run_dirs))}", file=sys.stderr)
    return 0


def cmd_compare(args) -> int:
    run_dirs = _run_dirs(args.run_dir)
    if len(run_dirs) < 2:
        raise UsageError("tcd compare needs at least two run directories (one run's figures: "
                         "tcd figures RUN_DIR)")
    labels = args.labels.split(",") if args.labels is not None else None
    if args.fit_setting is not None and args.target_peak is None:
        raise UsageError("--fit-setting names the setting that --target-peak fits: give "
                         "--target-peak MPa too")
    from .compare import compare_runs
    report: list[str] = []
    with _writing():
        written = _figure_warnings_as_lines(lambda: compare_runs(
            run_dirs, args.out, labels, args.seeds, target_peak=args.target_peak,
            setting=args.fit_setting, report=report))
    for path in written:
        print(path)
    for text in report:
        print(text.replace("**", ""))
    return 0


def cmd_view(args) -> int:
    path = _existing_file(args.file)
    from .viewer import view
    try:
        view(path, frame=args.frame, color=args.color)
    except RuntimeError as exc:     # no display or no Vulkan
        raise UsageError(str(exc)) from None
    return 0


def cmd_bench(args) -> int:
    """With --json, stdout holds the JSON alone: what else is printed meanwhile (Taichi's
    start-up lines among it) goes to stderr."""
    import contextlib
    with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
        result = _run_bench(args)
    _print_result(result, args.json)
    return 0


def _run_bench(args) -> dict:
    from . import bench
    run = getattr(bench, args.benchmark, None)
    if run is None:
        raise UsageError(f"this tcd has no '{args.benchmark}' benchmark (tcd.bench."
                         f"{args.benchmark} is missing)")
    if args.benchmark == "scaling":
        try:
            sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
        except ValueError:
            raise UsageError(f"--sizes {args.sizes!r}: expected comma-separated integers") \
                from None
        if not sizes or min(sizes) < 1 or max(sizes) > MAX_BENCH_PARTICLES:
            raise UsageError(f"--sizes {args.sizes!r}: expected positive particle counts, at "
                             f"most {MAX_BENCH_PARTICLES:.0e}")
        def done(row):
            print(f"scaling: N = {row['particles']}: {row['seconds_per_particle_step']:.3g} s per "
                  f"particle-step, {row['mean_sweeps']:.0f} mean sweeps, residual "
                  f"{row['final_residual']:.2g} ({row['pour_wall_s'] + row['loop_wall_s']:.0f} s)",
                  file=sys.stderr, flush=True)
        result = run(sizes=sizes, steps=args.steps, arch=args.arch, precision=args.precision,
                     tolerance=args.tolerance, out=args.out, progress=done,
                     schedule=args.schedule, threads=args.threads, colouring=args.colouring,
                     settle=args.settle, check_every=args.check_every,
                     **({"sweep_order": args.sweep_order} if args.sweep_order != "symmetric" else {}),
                     **({"warm_start_extrapolation": args.warm_start_extrapolation}
                        if args.warm_start_extrapolation else {}),
                     **({"convergence": args.convergence} if args.convergence != "impulse" else {}),
                     **({"acceleration": args.acceleration} if args.acceleration != "nncg" else {}))
    else:
        if getattr(args, "sample", None) and args.particles is not None:
            raise UsageError("--particles and --sample: the shear benchmark shears either a "
                             "sample it prepares of --particles grains or the prepared file "
                             "--sample gives; give one of them")
        options = dict(particles=5200 if args.particles is None else args.particles,
                       arch=args.arch, precision=args.precision,
                       tolerance=args.tolerance, seed=args.seed, schedule=args.schedule,
                       threads=args.threads, colouring=args.colouring,
                       check_every=args.check_every)
        if getattr(args, "samples", 1) > 1:
            options["samples"] = args.samples
        if getattr(args, "bond_solve", "blocks") != "blocks":
            options["bond_blocks"] = False
        if getattr(args, "renumber", False):
            options["renumber"] = True
        if args.sweep_order != "symmetric":
            options["sweep_order"] = args.sweep_order
        if args.warm_start_extrapolation:
            options["warm_start_extrapolation"] = args.warm_start_extrapolation
        if args.convergence != "impulse":
            options["convergence"] = args.convergence
        if args.acceleration != "nncg":
            options["acceleration"] = args.acceleration
        if getattr(args, "sample", None):
            for k in range(getattr(args, "samples", 1)):
                try:
                    path = Path(args.sample.format(seed=args.seed + k))
                except (KeyError, IndexError, ValueError):
                    raise UsageError(f"--sample {args.sample}: the only placeholder allowed is "
                                     "{seed}") from None
                if path.is_dir():
                    raise UsageError(f"--sample {args.sample}: {path} is a directory, not a "
                                     "prepared sample file")
                if not path.is_file():
                    raise UsageError(f"--sample {args.sample}: no such file {path}")
            options["sample"] = args.sample
        if args.time is not None:       # else the benchmark's own duration
            options["time"] = args.time
        if args.trace:
            if args.repeat > 1:
                raise UsageError("--trace with --repeat: every run would write the same trace; "
                                 "trace a single run")
            options["trace"] = args.trace
        result = median_run(run, options, args.repeat)
    return result


def median_run(run, options: dict, repeat: int) -> dict:
    """Run a benchmark `repeat` times with the same options (each run builds its own system;
    compilation is excluded from every timing) and return the run whose time per particle-step
    is the median, with every run's figure under `repeats_seconds_per_particle_step`."""
    runs = [run(**options) for _ in range(repeat)]
    if repeat == 1:
        return runs[0]
    order = sorted(range(repeat), key=lambda k: runs[k]["seconds_per_particle_step"])
    result = dict(runs[order[(repeat - 1) // 2]])
    result["repeats"] = repeat
    result["repeats_seconds_per_particle_step"] = [r["seconds_per_particle_step"] for r in runs]
    return result


# --- parser --------------------------------------------------------------------------------------
def _integer(text: str, low: int, words: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {words}, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"expected {words}, got {text}")
    return value


def _positive_int(text: str) -> int:
    return _integer(text, 1, "a positive integer")


#: the most particles `tcd bench` builds: the scenarios' bound on a layer (config's
#: MAX_PARTICLES_PER_LAYER); a larger count asked NumPy for an array it cannot index
MAX_BENCH_PARTICLES = 10**7     # = tcd.bench.MAX_PARTICLES


def _particle_count(text: str) -> int:
    value = _positive_int(text)
    if value > MAX_BENCH_PARTICLES:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_BENCH_PARTICLES:.0e} particles, "
                                         f"got {text}")
    return value


MAX_IMAGE_SIDE = 16384      # pixels: a larger image asked for tens of GiB of fields


def _image_side(text: str) -> int:
    value = _positive_int(text)
    if value > MAX_IMAGE_SIDE:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_IMAGE_SIDE} pixels, got {text}")
    return value


def _frame_rate(text: str) -> float:
    value = _positive_float(text)
    if not 0.01 <= value <= 1000.0:     # a GIF frame lasts at most 655 s, at least 1 ms
        raise argparse.ArgumentTypeError(f"expected a frame rate from 0.01 to 1000 per second, "
                                         f"got {text}")
    return value


def _non_negative_int(text: str) -> int:
    return _integer(text, 0, "an integer >= 0")


def _unit_interval(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text}")
    return value


def _seed_list(text: str) -> list:
    try:
        seeds = [int(w) for w in text.split(",") if w.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integer seeds, got {text!r}") from None
    if not seeds:
        raise argparse.ArgumentTypeError(f"expected at least one seed, got {text!r}")
    return seeds


def _setting(text: str) -> str:
    """A `--set KEY=VALUE` as given (checked here; applied by config.apply_settings)."""
    from .config import parse_setting
    try:
        parse_setting(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def _backend_options(parser, *, default_arch=None, default_precision=None, what=""):
    parser.add_argument("--arch", choices=ARCHS, default=default_arch,
                        help=f"Taichi backend{what}")
    parser.add_argument("--precision", choices=PRECISIONS, default=default_precision,
                        help=f"floating-point precision{what}")


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    parser = argparse.ArgumentParser(
        prog="tcd", description="Taichi Contact Dynamics: granular samples and Leutner shear "
                                "tests of asphalt-like materials (rigid spheres, bonds).")
    parser.add_argument("--version", action="version", version=f"tcd {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("run", help="run a scenario (TOML) and write its results",
                       description="Run every stage of a scenario for every seed. See "
                                   "docs/scenarios.md for the file format.")
    p.add_argument("scenario", metavar="SCENARIO.toml")
    p.add_argument("--out", metavar="DIR", help="output directory (default runs/<name>)")
    _backend_options(p, what=" (overrides [backend] of the scenario)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from its last checkpoint")
    p.add_argument("--jobs", type=_positive_int, default=1, metavar="N",
                   help="samples run at once, one process each (default 1; the CPU solver "
                        "uses one core per sample)")
    p.add_argument("--batch", action="store_true",
                   help="shear every sample at once in one batched simulation (a scenario whose "
                        "only stage is a shear of prepared samples; one sample per core on "
                        "the CPU, all at once on a GPU)")
    p.add_argument("--from", dest="from_run", metavar="RUN",
                   help="a new run that goes on from where run directory RUN's samples stand "
                        "(their checkpoints), with this scenario's solver or output settings, "
                        "or a longer shear (a larger displacement_mm; a finished shear is "
                        "reopened); RUN is only read (docs/usage.md, \"Going on from another "
                        "run\")")
    p.add_argument("--seeds", type=_seed_list, metavar="S1,S2,...",
                   help="run only these of the scenario's seeds (e.g. to split a study across "
                        "invocations; the summary then holds these samples, and with --resume "
                        "every sample finished in the --out directory)")
    p.add_argument("--set", action="append", type=_setting, metavar="KEY=VALUE",
                   help="set a scenario key for this run, without editing the file (repeat for "
                        "several): e.g. --set bond.yield_stress_MPa=1.6 --set "
                        "solver.tolerance=1e-6 --set stage[1].displacement_mm=1.0 (a stage "
                        "counted from 1; VALUE a TOML value or a bare word). The run's stored "
                        "scenario.toml holds the result; --resume needs the same --set")
    p.set_defaults(handler=cmd_run)

    p = sub.add_parser("info", help="summarise a tcd HDF5 file (states, series, checkpoint), "
                                    "a run directory (each sample: done, where it stopped, "
                                    "or not started) or a scenario file (checked: what a run "
                                    "of it would run, every setting with its defaults)")
    p.add_argument("file", metavar="FILE.h5|RUN_DIR|SCENARIO.toml")
    p.add_argument("--set", action="append", type=_setting, metavar="KEY=VALUE",
                   help="a scenario file: check it with these settings, as tcd run --set would run it")
    p.set_defaults(handler=cmd_info)

    p = sub.add_parser("render", help="render snapshots of a states file to an image or "
                                      "animation (offscreen)")
    p.add_argument("file", metavar="FILE.h5")
    p.add_argument("--out", required=True, metavar="IMAGE",
                   help="output: .png (one frame), .gif or .mp4 (animation)")
    p.add_argument("--frame", type=int, default=-1, metavar="K",
                   help="frame index for a still image (default -1: the last)")
    p.add_argument("--frames", metavar="all|K,K,...",
                   help="frames of an animation (default all)")
    p.add_argument("--color", choices=COLOR_MODES, default="layer")
    p.add_argument("--section", choices=SECTIONS, default=None,
                   help="cut away the half in front of this vertical plane through the axis")
    p.add_argument("--camera", choices=CAMERAS, default="iso")
    p.add_argument("--width", type=_image_side, default=1600)
    p.add_argument("--height", type=_image_side, default=1200)
    p.add_argument("--fps", type=_frame_rate, default=10.0,
                   help="animation frame rate (default 10; at most 50 in a GIF)")
    _backend_options(p, default_arch="cpu", default_precision="f64")
    p.set_defaults(handler=cmd_render)

    p = sub.add_parser("export", help="export snapshots to VTK files (.vtu + .pvd) for "
                                      "ParaView, VisIt or PyVista",
                       description="Write one .vtu file per part and frame (particles, "
                                   "contact and bond lines, wall surfaces) and one .pvd time "
                                   "series per part. FILE.h5: a states file, a prepared sample "
                                   "or a checkpoint. Arrays: see tcd/export.py.")
    p.add_argument("file", metavar="FILE.h5")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created)")
    p.add_argument("--frames", metavar="all|K,K,...", help="frames to export (default all; "
                   "negative indices count from the end)")
    p.add_argument("--parts", default="particles,contacts,bonds,walls", metavar="P,P,...",
                   help="any of particles, contacts, bonds, walls (default all four)")
    p.add_argument("--prefix", metavar="NAME", help="start of the file names (default the "
                   "file's name, e.g. states: states_particles_000000.vtu); exports of several "
                   "samples' states.h5 into one folder each need their own")
    p.set_defaults(handler=cmd_export)

    p = sub.add_parser("analyse", help="contact network, fabric and mean grain stress of every "
                                       "snapshot, as a series (.h5 and .csv)",
                       description="One row per frame: contact and bond counts, coordination, "
                                   "normal forces, the Love-Weber mean stress in the grains and "
                                   "the fabric tensor (see tcd/analysis.py). FILE.h5: a states "
                                   "file, a prepared sample or a checkpoint.")
    p.add_argument("file", metavar="FILE.h5")
    p.add_argument("--out", required=True, metavar="PREFIX",
                   help="writes PREFIX.h5 and PREFIX.csv")
    p.add_argument("--frames", metavar="all|K,K,...", help="frames (default all)")
    p.add_argument("--time-step", type=_positive_float, metavar="H",
                   help="time step (s) to turn impulses into forces, for a file without a "
                        "scenario (a checkpoint or prepared sample)")
    p.set_defaults(handler=cmd_analyse)

    p = sub.add_parser("figures", help="make the report figures of a run directory (or of the "
                                        "parts of one study, run with --seeds)")
    p.add_argument("run_dir", metavar="RUN_DIR", nargs="+",
                   help="a run directory; several: the parts of one study, shown together")
    p.add_argument("--out", metavar="DIR", help="where to write them (default: inside RUN_DIR; "
                                                "needed with several RUN_DIRs)")
    p.add_argument("--velocity", choices=("mean", "instant"), default="mean",
                   help="Fig. 3: each grain's mean velocity between two snapshots (the paper's "
                        "average velocity of the grains; default) or the snapshot's own")
    p.set_defaults(handler=cmd_figures)

    p = sub.add_parser("compare", help="several runs side by side (a parameter study): their "
                                        "shear curves, mean peaks and differing settings")
    p.add_argument("run_dir", metavar="RUN_DIR", nargs="+",
                   help="two or more run directories, of any scenarios")
    p.add_argument("--out", metavar="DIR", required=True,
                   help="where to write compare.png/.pdf/.md/.csv")
    p.add_argument("--labels", metavar="A,B,...",
                   help="one name per run (default: each directory's name)")
    p.add_argument("--seeds", type=_seed_list, metavar="S1,S2,...",
                   help="only these samples of each run (the same samples under each setting; "
                        "default: all)")
    p.add_argument("--target-peak", type=float, metavar="MPA",
                   help="calibrate: the value of the numeric setting in which the runs differ "
                        "at which the mean peak would be MPA (e.g. 0.898, the experiments'), "
                        "interpolated between the runs that bracket it (printed and in "
                        "compare.md)")
    p.add_argument("--fit-setting", metavar="KEY",
                   help="the dotted scenario key --target-peak fits, when the runs differ in "
                        "several (e.g. bond.yield_stress_MPa)")
    p.set_defaults(handler=cmd_compare)

    p = sub.add_parser("view", help="interactive viewer of a states file (needs a display)")
    p.add_argument("file", metavar="FILE.h5")
    p.add_argument("--frame", type=int, default=-1, metavar="K", help="first frame shown")
    p.add_argument("--color", choices=COLOR_MODES, default="layer")
    p.set_defaults(handler=cmd_view)

    p = sub.add_parser("bench", help="benchmarks: seconds per particle step, with accuracy")
    bench_sub = p.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True)
    for name, particles, text in (("pour", 2600, "pour spheres into a cylinder"),
                                  ("shear", 5200, "Leutner shear of a bonded sample")):
        b = bench_sub.add_parser(name, help=text)
        b.add_argument("--particles", type=_particle_count,
                       default=None if name == "shear" else particles, metavar="N",
                       help=f"particle count (default {particles})"
                       + ("; not with --sample, whose grains it shears" if name == "shear" else ""))
        b.add_argument("--time", type=_positive_float, default=None, metavar="T",
                       help="simulated seconds (default: the benchmark's own)")
        _backend_options(b, default_arch="cpu", default_precision="f64")
        b.add_argument("--tolerance", type=_positive_float, default=1e-4)
        _schedule_options(b)
        b.add_argument("--seed", type=_non_negative_int, default=1)
        b.add_argument("--json", action="store_true", help="print JSON instead of a table")
        b.add_argument("--repeat", type=_positive_int, default=1, metavar="N",
                       help="run N times and report the median run (all N figures listed)")
        b.add_argument("--trace", default=None, metavar="FILE.csv",
                       help="write one CSV row per timed step (step, time_s, sweeps, residual, "
                            "contacts, wall_s)")
        if name == "shear":
            b.add_argument("--sample", default=None, metavar="FILE.h5",
                           help="a prepared sample (prepared.h5 of a run) instead of a generated "
                                "one; {seed} in the name is replaced by the seed")
            b.add_argument("--samples", type=_positive_int, default=1, metavar="K",
                           help="shear K samples (seeds SEED..SEED+K-1) as one batched simulation")
            b.add_argument("--bond-solve", choices=("blocks", "pairs"), default="blocks",
                           help="bond items of the Gauss-Seidel: each particle's bonds solved "
                                "together (blocks, the default) or bond by bond (pairs)")
            b.add_argument("--renumber", action="store_true",
                           help="number the particles along the shear before bonding (the "
                                "stage's renumber = true): cheaper steps with --schedule "
                                "partitioned; another visiting order, so other sweep counts")
        b.set_defaults(handler=cmd_bench)
    b = bench_sub.add_parser("scaling", help="cost per particle step against particle count")
    b.add_argument("--sizes", default="1000,3000,10000,30000,100000", metavar="N,N,...")
    b.add_argument("--steps", type=_positive_int, default=200)
    b.add_argument("--settle", type=float, default=0.3, metavar="T",
                   help="simulated seconds poured before each size's timed steps (default 0.3)")
    _backend_options(b, default_arch="cpu", default_precision="f64")
    b.add_argument("--tolerance", type=_positive_float, default=1e-4)
    _schedule_options(b)
    b.add_argument("--out", default="renders/scaling", metavar="PREFIX",
                   help="writes PREFIX.csv and PREFIX.png (default renders/scaling)")
    b.add_argument("--json", action="store_true", help="print JSON instead of a table")
    b.set_defaults(handler=cmd_bench)
    return parser


def _schedule_options(parser) -> None:
    parser.add_argument("--schedule", choices=("auto", "serial", "partitioned", "coloured",
                                               "resident"),
                        default="auto", help="Gauss-Seidel schedule (default: serial on the "
                        "CPU, coloured on the GPU; resident: the coloured one with all sweeps "
                        "of a step in one launch)")
    parser.add_argument("--threads", type=_positive_int, default=2, metavar="P",
                        help="threads of the partitioned schedule (its numbers depend on P)")
    parser.add_argument("--sweep-order", choices=("forward", "symmetric"), default="symmetric",
                        help="Gauss-Seidel sweeps forward and backward in turn (default) or "
                             "all forward (fewer sweeps on a shear)")
    parser.add_argument("--acceleration", choices=("nncg", "none"), default="nncg",
                        help="conjugate-gradient momentum (NNCG) on the sweeps of the serial, "
                        "partitioned and resident schedules (default), or plain Gauss-Seidel")
    parser.add_argument("--warm-start-extrapolation", type=_unit_interval, default=0.0, metavar="C",
                        help="start each step's bonds and lasting contacts from R_n + C (R_n - "
                             "R_n-1) instead of the last impulse R_n (default 0; 0.5 saves "
                             "sweeps on a shear)")
    parser.add_argument("--colouring", choices=("auto", "greedy", "rounds"), default="auto",
                        help="colouring of the coloured schedule: greedy (serial), rounds "
                        "(parallel); default greedy on the CPU, rounds on the GPU")
    parser.add_argument("--convergence", choices=("impulse", "quad"), default="impulse",
                        help="convergence measure: the relative impulse change of a sweep "
                        "(default) or LMGC90's 'Quad ' check (QuadDV, QuadDVR, MeanDVoR all "
                        "below --tolerance)")
    parser.add_argument("--check-every", type=_positive_int, default=1, metavar="K",
                        help="sweeps between convergence checks (default 1; on a GPU each check "
                        "waits for the device)")


def _os_message(exc: OSError) -> str:
    """`PATH: reason` of the file system's refusal (the reason alone when it names no path)."""
    where = exc.filename if exc.filename is not None else ""
    return f"{where + ': ' if where else ''}{exc.strerror or exc}"


def _io_error(exc: OSError, args) -> int:
    """The file system refused (read-only, full, a name too long, a file where a folder must
    be): one line naming the path; every output is written atomically, so what was there
    before is intact."""
    if args.command != "run":
        hint = ""
    elif getattr(exc, "tcd_records_taken_back", False):
        # nothing of the run was left (its sample folders gone, moved or deleted while it ran):
        # its records were taken back, so there is nothing to resume
        hint = "; nothing of this run is left to resume: once this is fixed, run it again"
    else:
        hint = ("; the files written before are intact: once this is fixed, run it again "
                "(with --resume if it had written a checkpoint)")
    print(f"tcd: error: {_os_message(exc)}{hint}", file=sys.stderr)
    return EXIT_IO


def _error(message) -> int:
    print(f"tcd: error: {message}", file=sys.stderr)
    return EXIT_USAGE


def main(argv=None) -> int:
    """Run the `tcd` command with `argv` (default sys.argv[1:]); returns the exit status
    (argparse's own exits, --help, --version and usage errors, are returned, not raised)."""
    argv = _joined_frames(sys.argv[1:] if argv is None else list(argv))
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else EXIT_USAGE)
    try:
        if os.environ.get("SOURCE_DATE_EPOCH", "").strip():    # refused now, not at a write
            from . import io
            io.created_time()
        if args.command == "run":           # its own handlers: a stop at the end of a step
            from .signals import guard_report_streams
            guard_report_streams()          # a reader gone (`| head`, a closed terminal): it runs on
            return args.handler(args)
        from .signals import TermAsInterrupt
        with TermAsInterrupt():
            return args.handler(args)
    except BrokenPipeError:
        # the reader went away (`tcd info FILE | head`): stop quietly, as Unix tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        if args.command == "run" and getattr(args, "out_dir", None) is not None:
            print(f"\ninterrupted; resume with: {_resume_command(args)}", file=sys.stderr)
        else:
            print("\ninterrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (UsageError, ValueError, FileNotFoundError) as exc:
        if not (isinstance(exc, FileNotFoundError) and not isinstance(exc, ValueError)
                and exc.errno is not None and args.command == "run"):
            return _error(exc)
        # a run's inputs are checked before it starts: the system's "no such file" is then
        # about an output (an --out under a folder that cannot hold it, as /proc)
        return _io_error(exc, args)
    except OSError as exc:
        return _io_error(exc, args)
    except RuntimeError as exc:
        from .backend import BackendUnavailable    # imported late: `tcd --help` stays instant
        if isinstance(exc, BackendUnavailable):
            return _error(exc)
        raise


if __name__ == "__main__":
    raise SystemExit(main())
