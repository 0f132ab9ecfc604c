"""Benchmarks: seconds per particle per time step of the stepping loop, with the residual and
sweeps that bought it (speed is never reported without accuracy).

`pour`: N spheres of the binder-course table placed at random sites of a cubic lattice in a
150 mm column, poured by gravity into a 150 mm cylinder (particle friction 0.7, frictionless
walls), H = 2e-4 s, for T simulated seconds. Compile time is excluded: the first step is run
and timed apart.
"""
from __future__ import annotations

import math
import time

import numpy as np

from . import backend, packing, walls

CYLINDER_RADIUS = 0.075


def _init(arch, precision):
    backend.init(arch, precision)


def pour_setup(particles: int, seed: int, tolerance: float, *, radius: float = CYLINDER_RADIUS,
               course: str = "binder", max_sweeps: int = 1000):
    from .simulation import Simulation, SolverSettings
    rng = np.random.default_rng(seed)
    r = packing.course_radii(course, particles, rng)
    x = packing.lattice_column(r, 2 * radius, 0.0, rng, max_height=max(1.6, 1e-4 * particles))
    top = float(x[:, 2].max() + r.max())
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=radius, name="bottom"),
          walls.cylinder((0, 0, 0), (0, 0, 1), radius, (0.0, top + 0.01), name="mould")]
    sim = Simulation(r, x, walls=wl, friction=0.7,
                     settings=SolverSettings(tolerance=tolerance, max_sweeps=max_sweeps),
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


def _loop(sim, steps: int):
    """Step and time the loop; the first step (compilation) is timed apart."""
    t0 = time.perf_counter()
    sim.step()
    compile_s = time.perf_counter() - t0
    sweeps, residuals = [], []
    t0 = time.perf_counter()
    for _ in range(steps - 1):
        rec = sim.step()
        sweeps.append(rec.sweeps)
        residuals.append(rec.residual)
    loop_s = time.perf_counter() - t0
    return compile_s, loop_s, np.asarray(sweeps), np.asarray(residuals)


def pour(particles: int = 2600, time: float = 1.0, arch: str = "cpu", precision: str = "f64",
         tolerance: float = 1e-4, seed: int = 1) -> dict:
    _init(arch, precision)
    sim = pour_setup(particles, seed, tolerance)
    steps = max(2, int(round(time / sim.settings.time_step)))
    compile_s, loop_s, sweeps, residuals = _loop(sim, steps)
    out = {
        "benchmark": "pour",
        "seconds_per_particle_step": loop_s / (particles * (steps - 1)),
        "particles": particles, "steps": steps, "simulated_time_s": steps * sim.settings.time_step,
        "mean_sweeps": float(sweeps.mean()) if len(sweeps) else 0.0,
        "max_sweeps_hit": int(np.count_nonzero(sweeps >= sim.settings.max_sweeps)),
        "final_residual": float(residuals[-1]) if len(residuals) else 0.0,
        "tolerance": tolerance, "arch": arch, "precision": precision,
        "schedule": sim.schedule, "loop_wall_s": loop_s, "compile_wall_s": compile_s,
        "memory_bytes_per_particle": sim.memory_bytes() / particles,
    }
    out.update(bed_metrics(sim))
    return out
