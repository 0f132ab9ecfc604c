"""LMGC90's 'Quad' convergence check against tcd's on one impact-phase step of the pour.

tcd stops a step's sweeps when the relative impulse change of a sweep, sum |dR| / sum |R|, is
below the tolerance (PHYSICS.md section 6). LMGC90 (mod_nlgs, check type 'Quad ') evaluates,
every few sweeps and without updating anything, for each contact the correction that its
local solve would still make, in velocity: dV = W (R - R'), where R is the current impulse,
R' the local solve's answer and W the contact's diagonal block of the Delassus operator
(diag(wnn, wtt, wtt) in the contact frame for spheres). With R_m = (R + R') / 2 and sums over
the contacts whose R_m is not zero:

    WRWR = (|W R|^2 + |W R'|^2) / 2,   WRR = (W R . R + W R' . R') / 2
    QuadDV   = sqrt(sum |dV|^2 / sum WRWR)
    QuadDVR  = sqrt(mean |dV|^2 |R_m|^2) / mean WRR
    MeanDVoR = sum R_m . dV / sum WRR

and the step has converged when all three are below the tolerance in absolute value.

From a pour state in the impact phase (the state of benchmarks/solver_convergence.py: 2600
binder spheres of `tcd bench pour` at --time, cached in a pickle), the same step is solved
with a cap of k sweeps (and a tolerance never reached), and both checks are evaluated on the
result: tcd's measure of the last sweep and LMGC90's three norms (Simulation.quad_norms: the
check that `[solver] convergence = "quad"` applies, tcd/solver.py, quad_terms).

    python benchmarks/lmgc90_check.py [--time 0.48] [--sweeps 1,3,10,30,100,300,1000,3000]
        [--acceleration nncg|none] [--state /tmp/tcd_pour_state_T.pkl]

Session 22 (NNCG, the default): on the step at 0.48 s LMGC90's norms are STRICTER than
tcd's: after 1000 sweeps tcd's measure is 1.4e-4, QuadDV 2.3e-4, QuadDVR 5.7e-4
(docs/performance.md has the table).
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout
sys.path.insert(0, str(Path(__file__).resolve().parent))
from solver_convergence import impact_step, impact_step_parser, solve_capped  # noqa: E402



def main():
    a = impact_step_parser(__doc__.split("\n")[0], "1,3,10,30,100,300,1000,3000").parse_args()
    state, sim = impact_step(a)
    print(f"pour of {a.particles} spheres, the step at t = {a.time} s, serial, {a.acceleration}")
    print("| sweeps | tcd's measure, last sweep | QuadDV | QuadDVR | MeanDVoR | contacts "
          "| solve time (s) |")
    print("|---|---|---|---|---|---|---|")
    for k in [int(x) for x in a.sweeps.split(",")]:
        ct, wall, _ = solve_capped(sim, state, a.time, k, a.acceleration)
        q = sim.quad_norms()
        print(f"| {k} | {float(sim.stats.residual[None]):.2e} | {q['QuadDV']:.2e} | "
              f"{q['QuadDVR']:.2e} | {q['MeanDVoR']:+.2e} | {int(ct.total[None])} | "
              f"{wall:.3f} |", flush=True)
    sim.close()


if __name__ == "__main__":
    main()
