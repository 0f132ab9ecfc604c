"""Solver convergence and cost per contact update on one impact-phase step of the pour.

From a pour state in the impact phase (the grains raining onto the growing bed: 2600 binder
spheres of `tcd bench pour` at t = 0.48 s, about 6500 contacts), the SAME step is solved again
and again with a sweep cap k and a tolerance that is never reached, so the step runs exactly k
sweeps; the table gives the residual reached (sum |dR| / sum |R| of the last sweep) and the wall
time of the whole step (contact building included: it dominates at 10 sweeps) per sweep and
contact, for each solver variant:
  - serial, NNCG momentum (the default),
  - serial, plain symmetric Gauss-Seidel,
  - partitioned over 2 threads (tcd/partitioned.py), NNCG.
The state is made by pouring (about 1 min) and cached in a pickle.

    python benchmarks/solver_convergence.py [--particles 2600] [--time 0.48]
        [--sweeps 10,100,1000,3000] [--state /tmp/tcd_pour_state.pkl]

Session 9 (idle machine, `--sweeps 10,100,1000`): residual after 1000 sweeps 1.20e-4 (serial
NNCG, 30.7 ns), 1.94e-4 (plain, 21.9 ns), 1.16e-4 (partitioned x2, 20.5 ns of wall time).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import pickle
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout
import taichi as ti  # noqa: E402

import tcd  # noqa: E402
from tcd import bench  # noqa: E402
from tcd import solver as sk  # noqa: E402

VARIANTS = (("serial, NNCG", dict(schedule="serial", acceleration="nncg")),
            ("serial, plain GS", dict(schedule="serial", acceleration="none")),
            ("partitioned x2, NNCG", dict(schedule="partitioned", threads=2, acceleration="nncg")))


def pour_state(particles: int, t: float, path: str):
    if os.path.exists(path):
        with open(path, "rb") as f:
            saved = pickle.load(f)
        if saved["particles"] == particles and saved["time"] == t:
            return saved["state"]
    print(f"pouring {particles} spheres for {t} s to make the state ({path})", flush=True)
    sim = bench.pour_setup(particles, 1, 1e-4)
    for _ in range(int(round(t / sim.settings.time_step))):
        sim.step()
    state = sim.state_dict()
    sim.close()
    with open(path, "wb") as f:
        pickle.dump({"particles": particles, "time": t, "state": state}, f)
    return state


def impact_step_parser(description: str, sweeps: str) -> argparse.ArgumentParser:
    """The options of a study of one impact step (lmgc90_check.py, body_convergence.py)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--particles", type=int, default=2600)
    ap.add_argument("--time", type=float, default=0.48)
    ap.add_argument("--sweeps", default=sweeps)
    ap.add_argument("--acceleration", choices=("nncg", "none"), default="nncg")
    ap.add_argument("--state", default=None, help="pickle of the pour state (default "
                    "/tmp/tcd_pour_state_<time>.pkl; made by pouring if missing)")
    return ap


def impact_step(a):
    """tcd on the CPU in f64, the pour state of the options `a` and a pour simulation to
    solve its step in: (state, sim)."""
    tcd.init("cpu", "f64")
    state = pour_state(a.particles, a.time, a.state or f"/tmp/tcd_pour_state_{a.time}.pkl")
    return state, bench.pour_setup(a.particles, 1, 1e-4)


def solve_capped(sim, state, t, k, acceleration):
    """Step from `state` at time t through the serial solver with exactly k sweeps (a tolerance
    never reached); no integration after. Returns (contacts, solve wall time, the bodies' free
    velocities: those after the predictor, before the warm start)."""
    sim.settings = dataclasses.replace(sim.settings, max_sweeps=k, tolerance=1e-300,
                                       schedule="serial", acceleration=acceleration)
    sim.schedule = "serial"
    ct = begin_step(sim, state, t)
    v_free = sim.velocities()
    s = sim.settings
    p, wl, bd = sim.particles, sim.wall_fields, sim.bonds
    sk.apply_warm_start(p, ct, bd)
    t0 = time.perf_counter()
    sk.nlgs_serial(p, wl, ct, bd, sim.stats, s.max_sweeps, s.tolerance, s.check_every,
                   *sim._sweep_flags())
    ti.sync()
    return ct, time.perf_counter() - t0, v_free


def begin_step(sim, state, t):
    """Load `state` at time t and run the step up to its warm start (`Simulation._begin_step`).
    Returns the contacts; the caller applies the warm start (`solver.apply_warm_start`) and
    solves."""
    sim.load_state_dict(state)
    sim.time = t
    sim._begin_step()
    return sim.contacts

def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--particles", type=int, default=2600)
    ap.add_argument("--time", type=float, default=0.48)
    ap.add_argument("--sweeps", default="10,100,1000,3000")
    ap.add_argument("--state", default="/tmp/tcd_pour_state.pkl")
    a = ap.parse_args()
    tcd.init("cpu", "f64")
    state = pour_state(a.particles, a.time, a.state)
    sim = bench.pour_setup(a.particles, 1, 1e-4)
    print("| variant | sweeps | residual | contacts | ns per contact update |")
    print("|---|---|---|---|---|")
    for name, options in VARIANTS:
        for k in [int(s) for s in a.sweeps.split(",")]:
            sim.settings = dataclasses.replace(sim.settings, max_sweeps=k, tolerance=1e-300,
                                               **options)
            sim.schedule = sim.settings.schedule
            for rep in range(2):           # the first solve of a variant compiles
                sim.load_state_dict(state)        # the walls are fixed: only the clock
                sim.time = a.time
                t0 = time.perf_counter()
                rec = sim.step()
                wall = time.perf_counter() - t0
            print(f"| {name} | {rec.sweeps} | {rec.residual:.2e} | {rec.contacts} | "
                  f"{wall / rec.sweeps / rec.contacts * 1e9:.1f} |", flush=True)
    sim.close()


if __name__ == "__main__":
    main()
