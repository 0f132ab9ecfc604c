"""Creep of a bonded pair of grains under a constant pull (the Burgers law of PHYSICS.md section 4).

Two 8 mm grains touch along x and are bonded (the bitumen film). The first is held fixed; the
second is pulled away with a constant force F. The bond's opening then follows the Burgers creep
compliance, delta(t) = F J(t), with

    J(t) = 1/K_m + t/eta_m + (1/K_k) (1 - exp(-t K_k / eta_k)),

an instantaneous elastic jump, a delayed elastic part (time constant eta_k / K_k) and a
viscous flow. The script steps the pair with Contact Dynamics and prints the opening against
F J(t). The force stays far below the bond's yield force (sigma_y pi r^2).

The pair lies exactly along x. Off an axis, the time step of 5e-3 s is too large for a grain
free to roll about its one loaded bond (F H^2 / (m L) = 8.9 here, unstable above 5.6:
docs/physics.md, "Limitations found by the physics audit"); pass a time step of 2e-3 s or less to `run` then.

    python examples/bonded_creep.py [--force 2] [--time 30] [--mode burgers|paper] [--arch cpu|gpu]
"""
from __future__ import annotations

import argparse
import math

import numpy as np

# the paper's Burgers parameters (tcd's BondLaw defaults), SI
K_M, ETA_M, K_K, ETA_K = 2e6, 2e7, 2e6, 2e7


def creep_compliance(t):
    """J(t) (m/N) as PHYSICS.md section 4 writes it."""
    t = np.asarray(t, dtype=float)
    return 1.0 / K_M + t / ETA_M + (1.0 / K_K) * (1.0 - np.exp(-t * K_K / ETA_K))


def run(force: float = 2.0, time: float = 30.0, mode: str = "burgers", h: float = 5e-3,
        every: float = 1.0) -> dict:
    """Pull the bonded pair with `force` (N) for `time` s; every `every` s the time, the
    opening and F J(t). tcd.init must have been called."""
    from tcd.simulation import BondLaw, Simulation, SolverSettings

    r = 0.004
    sim = Simulation([r, r], [[0.0, 0.0, 0.0], [2 * r, 0.0, 0.0]], fixed=[True, False],
                     settings=SolverSettings(time_step=h, tolerance=1e-10, max_sweeps=200,
                                             gravity=(0.0, 0.0, 0.0)),
                     bond_law=BondLaw(mode=mode, maxwell_stiffness=K_M, maxwell_viscosity=ETA_M,
                                      kelvin_stiffness=K_K, kelvin_viscosity=ETA_K),
                     domain=((-0.02,) * 3, (0.04, 0.02, 0.02)))
    if sim.create_bonds(gap_tolerance=1e-6) != 1:
        raise RuntimeError("the pair should make exactly one bond")
    sim.set_external_force([[0.0, 0.0, 0.0], [force, 0.0, 0.0]])
    gap0 = float(np.linalg.norm(sim.positions()[1] - sim.positions()[0]) - 2 * r)
    rows = []
    k_every = max(1, int(round(every / h)))
    for k in range(1, int(round(time / h)) + 1):
        sim.step()
        if k % k_every == 0:
            x = sim.positions()
            opening = float(np.linalg.norm(x[1] - x[0]) - 2 * r) - gap0
            rows.append((k * h, opening, float(force * creep_compliance(k * h))))
    intact = sim.bonds_intact_count()
    sim.close()
    return {"rows": rows, "bonds_intact": intact,
            "yield_force": BondLaw().yield_stress * math.pi * r**2}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--force", type=float, default=2.0, help="pull (N)")
    ap.add_argument("--time", type=float, default=30.0, help="simulated time (s)")
    ap.add_argument("--mode", choices=("burgers", "paper"), default="burgers",
                    help="the bond law: implicit Burgers model, or the paper's secant law")
    ap.add_argument("--arch", choices=("cpu", "gpu"), default="cpu")
    a = ap.parse_args()
    import tcd
    tcd.init(a.arch, "f64")
    o = run(a.force, a.time, a.mode, every=max(a.time / 10, 5e-3))
    print(f"pull {a.force} N on a bonded pair ({a.mode} law; the bond yields at "
          f"{o['yield_force']:.0f} N)")
    print("| t (s) | opening (um) | F J(t) (um) | ratio |")
    print("|---|---|---|---|")
    for t, d, e in o["rows"]:
        print(f"| {t:.2f} | {d * 1e6:.4f} | {e * 1e6:.4f} | {d / e:.5f} |")
    print(f"bonds intact at the end: {o['bonds_intact']}")


if __name__ == "__main__":
    main()
