"""Solver convergence and cost per contact update on one impact-phase step of the pour.

Reproduces the solver measurements of the performance report: from a pour state in the impact
phase (default /tmp/state2300.pkl: 2600 particles at t = 0.45 s, about 6300 contacts), build
the contacts of the next step, warm-start them, then drive the Gauss-Seidel sweep by sweep and
print the residual (relative impulse change of the sweep, sum |dR| / sum |R|) at chosen sweep
counts, and the CPU time per contact update of
  - the one-launch serial kernel (`solver.nlgs_serial`), and
  - the two-thread partitioned schedule (`solver.nlgs_partitioned`, wall time and CPU time).
If the pickle is absent, the state is made by a short pour (--particles, --time).

    python benchmarks/solver_convergence.py [--state PATH] [--particles 1000] [--time 0.45]
        [--sweeps 1000] [--precision f64]

The pickle holds (radius, position, state_dict, time) of a `tcd.bench.pour_setup` run.
"""
from __future__ import annotations

import argparse
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout
import tcd  # noqa: E402
from tcd import bench, walls  # noqa: E402
from tcd import contacts as ck  # noqa: E402
from tcd import solver as sk  # noqa: E402
from tcd.simulation import Simulation  # noqa: E402

R = bench.CYLINDER_RADIUS


def make_state(particles: int, t: float, path: str | None):
    sim = bench.pour_setup(particles, 1, 1e-4)
    r = sim.radii()
    steps = int(round(t / sim.settings.time_step))
    for k in range(steps):
        sim.step()
    out = (r, sim.positions(), sim.state_dict(), sim.time)
    if path:
        with open(path, "wb") as f:
            pickle.dump(out, f)
    return out


def load(state_path: str, particles: int, t: float):
    if os.path.exists(state_path):
        with open(state_path, "rb") as f:
            return pickle.load(f)
    print(f"{state_path} absent: pouring {particles} particles for {t} s to make one")
    return make_state(particles, t, None)


def prepared(r, x, state, t):
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=R, name="bottom"),
          walls.cylinder((0, 0, 0), (0, 0, 1), R, (0.0, 1.6), name="mould")]
    sim = Simulation(r, x, walls=wl, friction=0.7, time=t,
                     domain=((-R, -R, -0.001), (R, R, float(x[:, 2].max()) + 0.01)))
    sim.load_state_dict(state)
    return sim


def start_step(sim):
    """Everything `Simulation._step` does before the sweeps."""
    s = sim.settings
    sim.load_state_dict(sim._saved)
    sim._move_walls(sim.time)
    sim._build_contacts()
    sk.predict(sim.particles, s.time_step, *s.gravity)
    ck.contact_geometry(sim.particles, sim.wall_fields, sim.contacts, s.time_step, s.theta,
                        sim.friction)
    sk.apply_warm_start(sim.particles, sim.contacts, sim.bonds)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--state", default="/tmp/state2300.pkl")
    ap.add_argument("--particles", type=int, default=1000)
    ap.add_argument("--time", type=float, default=0.45)
    ap.add_argument("--sweeps", type=int, default=1000)
    ap.add_argument("--precision", default="f64")
    a = ap.parse_args()
    tcd.init("cpu", a.precision)
    r, x, state, t = load(a.state, a.particles, a.time)
    sim = prepared(r, x, state, t)
    sim._saved = state
    p, wl, ct, bd, st = sim.particles, sim.wall_fields, sim.contacts, sim.bonds, sim.stats

    # residual trace (serial kernel, resumable: each call continues from the stored impulses)
    start_step(sim)
    m = int(ct.total[None])
    print(f"particles {sim.n}, contacts {m} ({int(np.count_nonzero(sim.contact_arrays()['j'] >= sim.n))} on walls)")
    marks = [k for k in (1, 2, 5, 10, 20, 50, 100, 200, 300, 500, 1000, 2000) if k <= a.sweeps]
    done = 0
    for k in marks:
        sk.nlgs_serial(p, wl, ct, bd, st, k - done, 1e-300, k - done, 0)
        done = k
        print(f"  after {k:5d} sweeps: residual {st.residual[None]:.2e}")

    # cost per contact update (CPU time; the partitioned schedule also in wall time)
    n = 200
    serial = lambda *a: sk.nlgs_serial(*a, 0)  # noqa: E731  (plain Gauss-Seidel)
    for name, solve in (("serial", serial), ("partitioned", sk.nlgs_partitioned)):
        for rep in range(2):          # the first call compiles
            start_step(sim)
            w0, c0 = time.perf_counter(), time.process_time()
            solve(p, wl, ct, bd, st, n, 1e-300, 1)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        print(f"{name:12s}: {wall / n / m * 1e9:6.1f} ns wall, {cpu / n / m * 1e9:6.1f} ns CPU per "
              f"contact update; residual after {n} sweeps {st.residual[None]:.2e}")
    if ct.partition is not None:
        s = ct.partition.start.to_numpy()
        print(f"partition: half 0 {s[1] - s[0]}, half 1 {s[2] - s[1]}, boundary {s[3] - s[2]} items")


if __name__ == "__main__":
    main()
