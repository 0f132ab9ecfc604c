"""Benchmarks: seconds per particle per time step of the stepping loop, with the residual and
sweeps that bought it (speed is never reported without accuracy).

`pour`: N spheres of the binder-course table placed at random sites of a cubic lattice in a
150 mm column, poured by gravity into a 150 mm cylinder (particle friction 0.7, frictionless
walls), H = 2e-4 s, for T simulated seconds. Compile time is excluded: the first
`WARMUP_STEPS` steps are run and timed apart.
"""
from __future__ import annotations

import math
import os
import pathlib
import time

import numpy as np

from . import backend, packing, walls
# the most particles a benchmark builds (the scenarios' bound on a layer) and the most steps it
# runs (a stage's bound: a step index the solver's 32-bit kernel arguments hold)
from .config import MAX_PARTICLES_PER_LAYER as MAX_PARTICLES, MAX_STAGE_STEPS as MAX_STEPS

CYLINDER_RADIUS = 0.075
SCALING_MIN_SIZE = 300
# Steps run before the timed loop, their time reported as compile_wall_s. Two, because the
# second step runs kernels that the first does not (the neighbour list reused rather than built,
# the warm start from the previous step), and compiling or loading them landed in the timed loop:
# with a fresh offline cache, the first timed step of `tcd bench shear` cost 4.6 s against
# 0.57 s for the next on the CPU (serial), 10.9 s against 0.99 s with the coloured schedule; on
# an H200 (session 33) the loop's first nine steps (steps 2-10) held 12.0 of its 18.0 s.
WARMUP_STEPS = 2


def _init(arch, precision):
    backend.init(arch, precision)


def pour_setup(particles: int, seed: int, tolerance: float, *, radius: float = CYLINDER_RADIUS,
               course: str = "binder", max_sweeps: int = 1000, schedule: str = "auto",
               threads: int = 2, colouring: str = "auto", check_every: int = 1,
               sweep_order: str = "symmetric", warm_start_extrapolation: float = 0.0,
               convergence: str = "impulse", acceleration: str = "nncg"):
    from .simulation import Simulation, SolverSettings
    rng = np.random.default_rng(seed)
    r = packing.course_radii(course, particles, rng)
    x = packing.lattice_column(r, 2 * radius, 0.0, rng, max_height=max(1.6, 1e-4 * particles))
    top = float(x[:, 2].max() + r.max())
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=radius, name="bottom"),
          walls.cylinder((0, 0, 0), (0, 0, 1), radius, (0.0, top + 0.01), name="mould")]
    sim = Simulation(r, x, walls=wl, friction=0.7,
                     settings=SolverSettings(tolerance=tolerance, max_sweeps=max_sweeps,
                                             schedule=schedule, threads=threads,
                                             colouring=colouring, check_every=check_every,
                                             sweep_order=sweep_order,
                                             warm_start_extrapolation=warm_start_extrapolation,
                                             convergence=convergence,
                                             acceleration=acceleration),
                     domain=((-radius, -radius, 0.0), (radius, radius, top)))
    return sim


def bed_metrics(sim, radius: float = CYLINDER_RADIUS) -> dict:
    x, r = sim.positions(), sim.radii()
    top = float((x[:, 2] + r).max())
    c = sim.contact_arrays()
    overlap = max(0.0, -float(c["gap"].min())) if len(c["gap"]) else 0.0
    rho = np.hypot(x[:, 0], x[:, 1]) + r
    volume = float(np.sum(4.0 / 3.0 * math.pi * r**3))
    return {
        "highest_top_m": top,
        "packing_fraction": volume / (math.pi * radius**2 * top),
        "max_overlap_ratio": overlap / (2.0 * float(r.min())),
        # escaped: centre outside the mould (small wall overlaps are in max_overlap_ratio)
        "outside": int(np.count_nonzero((rho - r > radius) | (x[:, 2] < 0.0))),
        "contacts": int(len(c["i"])),
    }


def _loop(sim, steps: int, per_system: bool = False):
    """Step and time the loop; the first `WARMUP_STEPS` steps (compilation) are timed apart.
    Sweeps and residual per timed step, or with `per_system` per timed step and batched system
    (steps x systems); `per_step`: each timed step's wall time (s), contacts and time at its
    end (s)."""
    t0 = time.perf_counter()
    for _ in range(WARMUP_STEPS):
        sim.step()
    compile_s = time.perf_counter() - t0
    sweeps, residuals, wall, contacts, clock = [], [], [], [], []
    t0 = time.perf_counter()
    last = t0
    for _ in range(steps - WARMUP_STEPS):
        rec = sim.step()
        now = time.perf_counter()
        sw, res = sim.system_stats() if per_system else (rec.sweeps, rec.residual)
        sweeps.append(sw)
        residuals.append(res)
        wall.append(now - last)
        contacts.append(rec.contacts)
        clock.append(rec.time)
        last = now
    loop_s = time.perf_counter() - t0
    colours = rec.colours if steps > WARMUP_STEPS else 0       # the last step's (coloured schedule)
    per_step = {"wall_s": np.asarray(wall), "contacts": np.asarray(contacts, dtype=np.int64),
                "time_s": np.asarray(clock)}
    return compile_s, loop_s, np.asarray(sweeps), np.asarray(residuals), colours, per_step


def _worst_over_systems(sweeps, residuals):
    """Per timed step, the most sweeps and the largest residual over batched systems (a
    (steps x systems) array from `_loop(per_system=True)`), or the arrays as they are."""
    sweeps, residuals = np.asarray(sweeps), np.asarray(residuals)
    if sweeps.ndim == 2:
        return sweeps.max(axis=1), residuals.max(axis=1)
    return sweeps, residuals


def phase_table(per_step: dict, sweeps, max_sweeps: int, windows: int = 10) -> list:
    """Where the loop's time went: the timed steps cut into `windows` runs of equal length
    (by step), each with its simulated time span, mean sweeps (`sweeps` per step, the worst
    over batched systems), steps at the sweep cap, mean contacts and share of the loop's
    wall time."""
    n = len(sweeps)
    m = min(windows, n)
    total = float(per_step["wall_s"].sum())
    out = []
    for k in range(m):
        a, b = k * n // m, (k + 1) * n // m          # m <= n: every window has a step
        w = float(per_step["wall_s"][a:b].sum())
        out.append({"time_s": [round(float(per_step["time_s"][a]), 6),
                               round(float(per_step["time_s"][b - 1]), 6)],
                    "steps": b - a, "mean_sweeps": round(float(sweeps[a:b].mean()), 2),
                    "max_sweeps_hit": int(np.count_nonzero(sweeps[a:b] >= max_sweeps)),
                    "mean_contacts": round(float(per_step["contacts"][a:b].mean()), 1),
                    "wall_s": round(w, 6), "wall_share": round(w / total, 4) if total > 0 else 0.0})
    return out


def writable_folder(folder: pathlib.Path, label: str, *, make: bool = False) -> None:
    """ValueError `label: cannot write into folder: reason` unless a file can be made in
    `folder` (created first with `make`): an output checked before a run, not after it."""
    import tempfile
    try:
        if make:
            folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ValueError(f"{label}: cannot write into {folder}: {exc.strerror or exc}") from None


def check_trace(path) -> None:
    """Refuse a trace path whose folder does not exist before the run, not after it."""
    if path:
        parent = pathlib.Path(path).parent
        if not parent.is_dir():
            raise FileNotFoundError(f"trace {path}: no such directory {parent}")
        if pathlib.Path(path).is_dir():
            raise ValueError(f"trace {path}: is a directory; give a file name, e.g. "
                             f"{pathlib.Path(path) / 'steps.csv'}")
        writable_folder(parent, f"trace {path}")   # a read-only one fails now, not after the run


def write_trace(path, per_step: dict, sweeps, residuals) -> pathlib.Path:
    """One CSV row per timed step (step, time_s, sweeps, residual, contacts, wall_s; `sweeps`
    and `residuals` per step, the worst over batched systems), written through
    io.atomic_path, so an interrupted write never leaves a partial trace."""
    import csv
    from . import io
    check_trace(path)
    path = pathlib.Path(path)
    with io.atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "time_s", "sweeps", "residual", "contacts", "wall_s"])
        for k in range(len(sweeps)):
            w.writerow([k + 1, f"{per_step['time_s'][k]:.6f}", int(sweeps[k]),
                        f"{residuals[k]:.6e}", int(per_step["contacts"][k]),
                        f"{per_step['wall_s'][k]:.6e}"])
    return path


def pour(particles: int = 2600, time: float = 1.0, arch: str = "cpu", precision: str = "f64",
         tolerance: float = 1e-4, seed: int = 1, schedule: str = "auto", threads: int = 2,
         colouring: str = "auto", check_every: int = 1, trace: str | None = None,
         sweep_order: str = "symmetric", warm_start_extrapolation: float = 0.0,
         convergence: str = "impulse", acceleration: str = "nncg") -> dict:
    """`schedule`, `threads`, `sweep_order`, `warm_start_extrapolation`, `convergence`,
    `acceleration`: the solver's
    (SolverSettings); `threads` only
    counts for the partitioned schedule. `trace`: a CSV path for one row per timed step (write_trace)."""
    _check_steps(time)              # what can be refused is, before Taichi starts
    check_trace(trace)
    _init(arch, precision)
    try:
        sim = pour_setup(particles, seed, tolerance, schedule=schedule, threads=threads,
                         colouring=colouring, check_every=check_every, sweep_order=sweep_order,
                         warm_start_extrapolation=warm_start_extrapolation,
                         convergence=convergence, acceleration=acceleration)
    except packing.ColumnTooTall as exc:
        raise ValueError(f"{exc}: the pour benchmark keeps the 150 mm mould; for more spheres "
                         f"use `tcd bench scaling --sizes {particles}`, whose cylinder widens "
                         "with N") from None
    steps = int(round(time / sim.settings.time_step))
    compile_s, loop_s, sweeps, residuals, colours, per_step = _loop(sim, steps)
    out = {
        "benchmark": "pour",
        "seconds_per_particle_step": loop_s / (particles * (steps - WARMUP_STEPS)),
        "particles": particles, "steps": steps, "simulated_time_s": steps * sim.settings.time_step,
        "mean_sweeps": float(sweeps.mean()) if len(sweeps) else 0.0,
        "max_sweeps_hit": int(np.count_nonzero(sweeps >= sim.settings.max_sweeps)),
        "final_residual": float(residuals[-1]) if len(residuals) else 0.0,
        "tolerance": tolerance, "check_every": sim.settings.check_every, "arch": arch,
        "precision": precision, "schedule": sim.schedule, "colours": colours,
        "sweep_order": sim.sweep_order_used,
        "warm_start_extrapolation": sim.settings.warm_start_extrapolation,
        "convergence": sim.settings.convergence,
        "acceleration": sim.acceleration_used,
        **({"resident": sim.resident_block} if sim.resident_block else {}),
        "loop_wall_s": loop_s, "compile_wall_s": compile_s,
        "memory_bytes_per_particle": sim.memory_bytes() / particles,
    }
    if sim.schedule == "partitioned":
        out["threads"] = threads
    out.update(bed_metrics(sim))
    worst_sweeps, worst_residuals = _worst_over_systems(sweeps, residuals)
    out["phases"] = phase_table(per_step, worst_sweeps, sim.settings.max_sweeps)
    if trace:
        out["trace"] = str(write_trace(trace, per_step, worst_sweeps, worst_residuals))
    return out


def _check_steps(time: float, time_step: float | None = None) -> None:
    """The first `WARMUP_STEPS` steps compile and are not timed: a benchmark needs one step
    more (`time_step`: the simulation's, by default the solver's default)."""
    if time_step is None:
        from .simulation import SolverSettings
        time_step = SolverSettings.time_step
    need = WARMUP_STEPS + 1
    # the steps the benchmark would run (3 x 2e-4 is 6.000000000000001e-4 in floating point)
    if not (math.isfinite(time) and int(round(time / time_step)) >= need):
        raise ValueError(f"time {time:g} s is less than {need} time steps ({need} x {time_step:g} s): "
                         f"the first {WARMUP_STEPS} steps compile and are not timed")
    if time / time_step > MAX_STEPS:        # (1e300 s ran for ever)
        raise ValueError(f"time {time:g} s is more than {MAX_STEPS:.2g} time steps of "
                         f"{time_step:g} s")


def _sample_path(particles: int, seed: int):
    # v2: the prepared.h5 format of `tcd run` (walls, time, domain), loaded by protocols.Shear
    return pathlib.Path("runs") / "bench" / f"sample_{particles}_{seed}_v2.h5"


def bench_sample(particles: int, seed: int, tolerance: float):
    """Path of a confined two-layer sample for the shear benchmark, generated once and cached
    under runs/bench/ (same file format as a `tcd run` prepared.h5): a quick pour (looser
    solver, larger step) of both courses into the 150 mm mould, then a top plate at the bed
    surface. Good enough to time the shear stage; the paper's preparation protocol is
    `tcd run scenarios/prepare.toml`."""
    from . import io
    from .simulation import Simulation, SolverSettings
    path = _sample_path(particles, seed)
    if path.exists():
        return path
    rng = np.random.default_rng(seed)
    half = particles // 2
    r = np.concatenate([packing.course_radii("binder", half, rng),
                        packing.course_radii("surface", particles - half, rng)])
    x = packing.lattice_column(r, 2 * CYLINDER_RADIUS, 0.0, rng, max_height=max(1.6, 1e-4 * particles))
    layer = np.r_[np.zeros(half, np.int32), np.ones(particles - half, np.int32)]
    top = float(x[:, 2].max() + r.max())
    R = CYLINDER_RADIUS
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=R), walls.cylinder((0, 0, 0), (0, 0, 1), R, (0, top + 0.01))]
    domain = ((-R, -R, 0.0), (R, R, top))
    sim = Simulation(r, x, layer=layer, walls=wl, friction=0.7,
                     settings=SolverSettings(time_step=5e-4, tolerance=max(tolerance, 1e-3), max_sweeps=200),
                     domain=domain)
    for _ in range(int(1.2 / 5e-4)):
        sim.step()
    xs, rs = sim.positions(), sim.radii()
    z_top = float((xs[:, 2] + rs).max())
    sim.set_walls(wl + [walls.plane((0, 0, z_top), (0, 0, -1), radius=R)])
    sim.set_velocities(np.zeros((particles, 3)))
    path.parent.mkdir(parents=True, exist_ok=True)
    io.save_checkpoint(path, sim.state_dict(), {"walls": [w.to_dict() for w in sim.walls], "time": sim.time,
                                                "domain": [list(map(float, d)) for d in domain]})
    sim.close()
    return path


def shear(particles: int = 5200, time: float = 0.2, arch: str = "cpu", precision: str = "f64",
          tolerance: float = 1e-4, seed: int = 1, sample: str | None = None, samples: int = 1,
          schedule: str = "auto", threads: int = 2, colouring: str = "auto",
          bond_blocks: bool = True, check_every: int = 1, trace: str | None = None,
          sweep_order: str = "symmetric", warm_start_extrapolation: float = 0.0,
          convergence: str = "impulse", acceleration: str = "nncg",
          renumber: bool = False) -> dict:
    """The shear stage of a run (protocols.Shear: bonds with the paper's law and tolerance,
    split rings, top plate on the highest grain, 50 mm/min) on a prepared sample, for `time`
    simulated seconds (the full test is 3 s: 15000 steps). `sample`: a prepared sample
    (`prepared.h5` of a `tcd run`, 150 mm mould) instead of the generated one; `particles`
    is then its own count; a `{seed}` in it is replaced by the seed.

    `samples` > 1: that many samples (seeds seed, seed + 1, ...) sheared at once as one batched
    simulation (Simulation.batch: the same fields, one step for all); the figure is then the
    wall time over (all particles x steps), and `per_sample` lists each system's sweeps and
    residual. Each sample starts its shear at the latest of their preparation clocks (a batch
    has one clock). `renumber`: the stage's `renumber` (particles numbered along the shear
    before bonding)."""
    from .config import parse_scenario
    from .runner import plan_shears
    from .simulation import Simulation
    from .state import MAX_SYSTEMS
    if not 1 <= samples <= MAX_SYSTEMS:
        raise ValueError(f"samples must be 1 to {MAX_SYSTEMS} (the systems one simulation "
                         f"batches), got {samples}")
    check_trace(trace)
    _init(arch, precision)
    seeds = [seed + k for k in range(samples)]
    paths = [pathlib.Path(sample.format(seed=s)) if sample else bench_sample(particles, s, tolerance)
             for s in seeds]
    for path in paths:
        if not path.is_file():
            raise FileNotFoundError(f"prepared sample {path}: no such file")
    scn = parse_scenario(f'name = "bench_shear"\nseeds = {seeds}\n'
                         f'[backend]\narch = "{arch}"\nprecision = "{precision}"\n'
                         f'[solver]\ntolerance = {float(tolerance)!r}\nschedule = "{schedule}"\n'
                         f'threads = {int(threads)}\ncolouring = "{colouring}"\n'
                         f'bond_blocks = {"true" if bond_blocks else "false"}\n'
                         f'check_every = {int(check_every)}\nsweep_order = "{sweep_order}"\n'
                         f'warm_start_extrapolation = {float(warm_start_extrapolation)!r}\n'
                         f'convergence = "{convergence}"\nacceleration = "{acceleration}"\n'
                         f'[[stage]]\nkind = "shear"\nsample = {str(paths[0].resolve())!r}\n'
                         f'renumber = {"true" if renumber else "false"}\n'
                         # the benchmark's problem as in every figure of the README (sessions
                         # 8-31): rings prolonged past their ends, not the default rim
                         'ring_edges = "extended"\n',
                         "<bench shear>")
    sims, phases = plan_shears(scn, scn.stages[0], seeds, paths)
    sim = sims[0] if samples == 1 else Simulation.batch(sims)
    if samples > 1:
        for o in sims:
            o.close()
    particles = sim.n
    bonds = sum(int(ph.info["bonds_created"]) for ph in phases)
    _check_steps(time, sim.settings.time_step)
    steps = int(round(time / sim.settings.time_step))
    compile_s, loop_s, sweeps, residuals, colours, per_step = _loop(sim, steps, per_system=True)
    out = {
        "benchmark": "shear", "seconds_per_particle_step": loop_s / (particles * (steps - WARMUP_STEPS)),
        "particles": particles, "samples": samples, "steps": steps,
        "simulated_time_s": steps * sim.settings.time_step,
        "bonds": bonds, "bonds_intact": sim.bonds_intact_count(),
        "mean_sweeps": float(sweeps.mean()),
        "max_sweeps_hit": int(np.count_nonzero(sweeps >= sim.settings.max_sweeps)),
        "final_residual": float(residuals[-1].max()), "tolerance": tolerance,
        "check_every": sim.settings.check_every, "arch": arch,
        "precision": precision, "schedule": sim.schedule, "colours": colours,
        "bond_solve": "blocks" if sim.settings.bond_blocks else "pairs",
        "sweep_order": sim.sweep_order_used,
        "warm_start_extrapolation": sim.settings.warm_start_extrapolation,
        "convergence": sim.settings.convergence,
        "acceleration": sim.acceleration_used,
        **({"resident": sim.resident_block} if sim.resident_block else {}),
        "renumber": bool(renumber),
        **({"threads": threads} if sim.schedule == "partitioned" else {}), "loop_wall_s": loop_s,
        "compile_wall_s": compile_s, "memory_bytes_per_particle": sim.memory_bytes() / particles,
        "contacts": int(sim.contact_arrays()["i"].size),
        "max_overlap_ratio": bed_metrics(sim)["max_overlap_ratio"],
    }
    if samples > 1:
        out["per_sample"] = [{"seed": s, "particles": int(sim.system_start[k + 1] - sim.system_start[k]),
                              "mean_sweeps": float(sweeps[:, k].mean()),
                              "final_residual": float(residuals[-1, k])}
                             for k, s in enumerate(seeds)]
    worst_sweeps, worst_residuals = _worst_over_systems(sweeps, residuals)
    out["phases"] = phase_table(per_step, worst_sweeps, sim.settings.max_sweeps)
    if trace:
        out["trace"] = str(write_trace(trace, per_step, worst_sweeps, worst_residuals))
    sim.close()
    return out


def scaling(sizes=(1000, 3000, 10000, 30000, 100000), steps: int = 200, arch: str = "cpu",
            precision: str = "f64", tolerance: float = 1e-4, out: str = "renders/scaling",
            progress=None, schedule: str = "auto", threads: int = 2,
            colouring: str = "auto", settle: float = 0.3, check_every: int = 1,
            sweep_order: str = "symmetric", warm_start_extrapolation: float = 0.0,
            convergence: str = "impulse", acceleration: str = "nncg") -> dict:
    """Seconds per particle per step against N: a settled-bed-like state is not needed here;
    each size pours a column of N binder-course spheres into a cylinder whose cross-section
    grows with N (same column height), timed over `steps` steps after `settle` s of pouring
    (0.3 s by default: the lower part of the column has landed; a GPU's 1e6 row may take less,
    the row records it).

    The CSV and the plot are rewritten (atomically) after every size, so an interrupted scan
    keeps the sizes it finished; `progress(row)` is called with each finished row. Sizes,
    steps and the output folder are checked before the first size runs."""
    sizes = [int(n) for n in sizes]
    if not sizes or min(sizes) < SCALING_MIN_SIZE:
        raise ValueError(f"sizes {sizes}: the scaling benchmark needs at least "
                         f"{SCALING_MIN_SIZE} spheres per size (its cylinder narrows as "
                         "sqrt(N), and below that it is too narrow for the 1.6 m lattice column)")
    if max(sizes) > MAX_PARTICLES:
        raise ValueError(f"sizes {sizes}: at most {MAX_PARTICLES:.0e} spheres per size")
    if not WARMUP_STEPS + 1 <= steps <= MAX_STEPS:
        raise ValueError(f"steps {steps}: at least {WARMUP_STEPS + 1} (the first {WARMUP_STEPS}, "
                         f"which compile, are not timed), at most {MAX_STEPS}")
    from .simulation import SolverSettings
    if not (math.isfinite(settle) and 0.0 <= settle <= MAX_STEPS * SolverSettings.time_step):
        raise ValueError(f"settle {settle}: expected a finite time >= 0 s, at most "
                         f"{MAX_STEPS:.2g} time steps")
    base = pathlib.Path(out)
    for folder in (base.parent, *base.parent.parents):
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"--out {out}: {folder} is a file, not a folder")
    writable_folder(base.parent, f"--out {out}", make=True)   # fails now, not after hours
    for path in scaling_paths(out):
        if (path.exists() or path.is_symlink()) and not path.is_file():
            raise ValueError(f"--out {out}: {path} exists and is not a file (a directory?): "
                             "remove it or choose another prefix")
    _init(arch, precision)
    rows = []
    for n in sizes:
        radius = CYLINDER_RADIUS * math.sqrt(max(n, 1) / 2600.0)
        sim = pour_setup(int(n), 1, tolerance, radius=radius, schedule=schedule, threads=threads,
                         colouring=colouring, check_every=check_every, sweep_order=sweep_order,
                         warm_start_extrapolation=warm_start_extrapolation,
                         convergence=convergence, acceleration=acceleration)
        t0 = time.perf_counter()
        for _ in range(int(round(settle / sim.settings.time_step))):
            sim.step()
        pre_s = time.perf_counter() - t0
        compile_s, loop_s, sweeps, residuals, colours, _ = _loop(sim, steps)
        contacts = int(sim.contact_arrays()["i"].size)
        rows.append({"particles": int(n), "seconds_per_particle_step": loop_s / (n * (steps - WARMUP_STEPS)),
                     "mean_sweeps": float(sweeps.mean()), "final_residual": float(residuals[-1]),
                     "max_sweeps_hit": int(np.count_nonzero(sweeps >= sim.settings.max_sweeps)),
                     "contacts": contacts,
                     "seconds_per_contact_sweep": loop_s / max(1.0, float(sweeps.sum())) /
                     max(1, contacts),
                     "memory_bytes_per_particle": sim.memory_bytes() / n,
                     "timed_steps": steps - WARMUP_STEPS, "loop_wall_s": loop_s, "pour_wall_s": pre_s,
                     "settle_s": float(settle)})
        sim.close()
        _write_scaling(rows, out, arch, precision, schedule, threads)
        if progress is not None:
            progress(rows[-1])
    csv_path, png_path = scaling_paths(out)
    return {"benchmark": "scaling", "arch": arch, "precision": precision, "rows": rows,
            "csv": str(csv_path), "plot": str(png_path)}


def scaling_paths(out) -> tuple[pathlib.Path, pathlib.Path]:
    """The CSV and the plot of `tcd bench scaling --out PREFIX`: PREFIX.csv and PREFIX.png
    (a dot inside PREFIX is kept: `renders/scaling.v2` gives renders/scaling.v2.csv; a PREFIX
    that already ends in .csv or .png stands for the pair)."""
    text = os.fspath(out)
    for suffix in (".csv", ".png"):
        if text.lower().endswith(suffix):
            text = text[:-len(suffix)]
            break
    return pathlib.Path(text + ".csv"), pathlib.Path(text + ".png")


def _write_scaling(rows: list, out: str, arch: str, precision: str, schedule: str = "auto",
                   threads: int = 2) -> None:
    """The scan so far as CSV and log-log plot (both replaced atomically)."""
    import csv
    from . import io
    csv_path, png_path = scaling_paths(out)
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(csv_path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.loglog([r["particles"] for r in rows], [r["seconds_per_particle_step"] for r in rows], "o-",
              label=f"tcd ({arch}, {precision}, "
              + (f"partitioned on {threads} threads)" if schedule == "partitioned" else f"{schedule})"))
    ax.loglog([r["particles"] for r in rows], [r["seconds_per_contact_sweep"] * 1e3 for r in rows], "s--",
              label="s per contact update x 1e3")
    ax.set_xlabel("particles N")
    ax.set_ylabel("s per particle per step")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with io.atomic_path(png_path) as tmp:
        io.save_figure(fig, tmp, "png", dpi=120)
    plt.close(fig)
