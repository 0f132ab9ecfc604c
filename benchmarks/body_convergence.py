"""A convergence measure on the bodies against tcd's impulse measure, on one impact step of the pour.

tcd stops a step's sweeps when a sweep's relative impulse change, sum |dR| / sum |R| over the
contacts, is below the tolerance. A rigid, hyperstatic, frictional bed has many force networks:
a sweep can move impulses along self-stresses (H^T dR = 0) that change no body's velocity. A
measure on the bodies would ignore those moves:

    body measure = sum_i m_i |v_i(k+1) - v_i(k)| / sum_i m_i |v_i(k) - v_free_i|

(the momentum one more sweep would still give the bodies, over the momentum the contacts gave
them). If it fell below the tolerance much sooner than the impulse measure, with the bodies'
velocities as close to a converged solve, it would be a lever for the pour (issue 2). From the
pour state of benchmarks/solver_convergence.py (2600 binder spheres at --time, cached in a
pickle), the same step is solved with a cap of k and of k + 1 sweeps (tolerance never reached),
and against a reference solved with 3 max(k) sweeps:

    python benchmarks/body_convergence.py [--time 0.48] [--sweeps 10,30,100,300,1000,3000]
        [--acceleration nncg|none]

Session 41 (serial, NNCG, the step at 0.48 s): the body measure is 8-11 times the impulse
measure at every k (at 1000 sweeps 1.15e-3 against 1.33e-4), so it is the stricter one and no
lever; the bodies' momentum is then 7.3 % away from the reference's (sum m |v - v_ref| over the
contacts' sum m |v_ref - v_free|), the impulses 19 %.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout
sys.path.insert(0, str(Path(__file__).resolve().parent))
from solver_convergence import impact_step, impact_step_parser, solve_capped  # noqa: E402


def solve(sim, state, t, k, acceleration):
    """The step at t solved with exactly k sweeps: the bodies' free and final velocities,
    masses, the impulses and tcd's measure of the last sweep."""
    _, _, v_free = solve_capped(sim, state, t, k, acceleration)
    return dict(v=sim.velocities(), v_free=v_free,
                m=1.0 / sim.particles.inv_mass.to_numpy()[:sim.n],
                impulse=sim.contact_arrays()["impulse"],
                residual=float(sim.stats.residual[None]))


def momentum(dv, m):
    return float(np.sum(m * np.linalg.norm(dv, axis=1)))


def main():
    a = impact_step_parser(__doc__.split("\n")[0], "10,30,100,300,1000,3000").parse_args()
    state, sim = impact_step(a)
    ks = [int(x) for x in a.sweeps.split(",")]
    ref = solve(sim, state, a.time, 3 * max(ks), a.acceleration)
    ref_momentum = momentum(ref["v"] - ref["v_free"], ref["m"])
    ref_impulse = float(np.sum(np.linalg.norm(ref["impulse"], axis=1)))
    print(f"pour of {a.particles} spheres, the step at t = {a.time} s, serial, "
          f"{a.acceleration}; reference: {3 * max(ks)} sweeps, impulse measure "
          f"{ref['residual']:.2e}")
    print("| sweeps | impulse measure (tcd's) | body measure | bodies' momentum vs reference "
          "| impulses vs reference |")
    print("|---|---|---|---|---|")
    for k in ks:
        x = solve(sim, state, a.time, k, a.acceleration)
        y = solve(sim, state, a.time, k + 1, a.acceleration)
        body = momentum(y["v"] - x["v"], x["m"]) / momentum(x["v"] - x["v_free"], x["m"])
        v_err = momentum(x["v"] - ref["v"], x["m"]) / ref_momentum
        r_err = float(np.sum(np.linalg.norm(x["impulse"] - ref["impulse"], axis=1))) / ref_impulse
        print(f"| {k} | {x['residual']:.2e} | {body:.2e} | {v_err:.2e} | {r_err:.2e} |",
              flush=True)
    sim.close()


if __name__ == "__main__":
    main()
