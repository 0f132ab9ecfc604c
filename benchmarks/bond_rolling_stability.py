"""The rolling instability of a loaded bond (docs/physics.md, "Limitations"): two 2 mm grains,
the first fixed, bonded at contact and pulled apart along their bond by F, the second nudged
sideways at 1e-12 m/s, stepped at H for a number of steps. Prints, per F, the stability number
F H^2 / (m L) (m the free grain's mass, L = 2 r the distance of the centres), how far the free
grain ends off the axis and how fast it moves, and the bonds' state counts (intact, broken in
tension, broken in shear). A frame frozen at the step's start makes the grain's rolling about
its partner an explicit pendulum, stable below F H^2 / (m L) = 4 x 7/5 = 5.6; with
`--bond-frame end` (the frame turned over the step, plain sweeps) it is stable at any force.

    python benchmarks/bond_rolling_stability.py [--forces 1,3,3.1,5] [--time-step 2e-4] [--steps 200] [--bond-frame start|end]
"""
from __future__ import annotations

import argparse
import math
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))     # run from a checkout
import tcd  # noqa: E402


def run(force: float, h: float, steps: int, radius: float = 1e-3, density: float = 2600.0,
        bond_frame: str = "start") -> dict:
    from tcd.simulation import Simulation, SolverSettings
    axis = np.array([0.0, 0.0, 1.0])
    x = np.array([[0.0, 0.0, 0.0], 2 * radius * axis])
    sim = Simulation([radius, radius], x, fixed=[True, False], density=density,
                     settings=SolverSettings(time_step=h, tolerance=1e-10, max_sweeps=2000,
                                             gravity=(0.0, 0.0, 0.0), bond_frame=bond_frame,
                                             acceleration="none" if bond_frame == "end" else "nncg"),
                     domain=((-0.05,) * 3, (0.05,) * 3))
    sim.create_bonds(1e-9)
    sim.set_velocities([[0.0, 0.0, 0.0], [1e-12, 0.0, 0.0]])
    sim.set_external_force([[0.0, 0.0, 0.0], list(force * axis)])
    sim.step(steps)
    p = sim.positions()[1]
    mass = density * 4.0 / 3.0 * math.pi * radius**3
    return {"force_N": force, "stability_number": force * h * h / (mass * 2 * radius),
            "off_axis_m": float(np.linalg.norm(p - axis * (p @ axis))),
            "speed_m_per_s": float(np.linalg.norm(sim.velocities()[1])),
            "bonds": sim.bonds_state_counts()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--forces", default="1,3,3.1,5", help="N, comma-separated")
    ap.add_argument("--time-step", type=float, default=2e-4)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--bond-frame", choices=("start", "end"), default="start")
    ap.add_argument("--arch", default="cpu")
    a = ap.parse_args(argv)
    tcd.init(a.arch, "f64")
    for f in (float(v) for v in a.forces.split(",")):
        r = run(f, a.time_step, a.steps, bond_frame=a.bond_frame)
        print(f"F = {f:g} N  F H^2/(m L) = {r['stability_number']:.2f}  off the axis "
              f"{r['off_axis_m']:.3e} m  speed {r['speed_m_per_s']:.3e} m/s  bonds "
              f"(intact, tension, shear) {r['bonds']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
