"""How far the pour's impact step is from long-run solutions when the solver stops: a check of
what tcd's measure at 1e-4 means there (session 26).

The state of `solver_convergence.py` (2600 spheres of `tcd bench pour` at t = 0.48 s) is
solved from the same warm start by `solver.nlgs_serial` (symmetric sweeps, plain or NNCG) for
k sweeps, and compared with reference solves of many sweeps: relative L1 differences of the
contact impulses and of the particle velocities.

    python benchmarks/pour_reference.py [--references plain:100000,nncg:100000]
        [--sweeps nncg:1138,plain:1832,plain:30000]
    python benchmarks/pour_reference.py --drift

Session 26 (this 2-core CPU, f64): the references stall, plain 1.71e-5 and NNCG 1.28e-5 after
100000 sweeps (plain 4.78e-5 after 30000), 11 % apart in impulses and 0.35 % in velocities.
The benchmark's stops (NNCG 1138 sweeps, measure 1.28e-4; plain 1832, 1.25e-4) are 33 % off
either in impulses and 1.0 % in velocities (warm start: 53 % and 4.6 %; 300 NNCG sweeps: 38 %
and 1.2 %). The forces of the rigid hyperstatic frictional bed are not unique; its velocities
settle to about 1 % long before the measure reaches 1e-4.
`--drift` (plain sweeps): after 100 / 1000 / 3000 sweeps, a change over two sweeps of 2.0e-3 /
3.0e-4 / 1.3e-4 of the impulses moves the bodies little (dR.W.dR / dR.D.dR = 1.3e-2 / 2.8e-3 /
2.0e-3, against 1 for a generic direction; velocities 2.0e-4 / 1.9e-5 / 7.5e-6), so the
measure mostly follows the force network's drift. The particles' resultants change as much as
the impulses, though (3.5e-3 / 3.1e-4 / 1.3e-4: the resultants are small beside the impulses
they sum), so a measure on resultants would stop no sooner.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import tcd  # noqa: E402
import solver_convergence  # noqa: E402
from coarse_correction import Step, body_response, delassus_diagonal  # noqa: E402


def resultants(d):
    """Each particle's resultant contact impulse and moment / radius (H^T R, unweighted)."""
    ones = np.ones(len(d["x"]))
    return body_response(d, d["r"], ones, ones)


def drift(step, marks=(10, 100, 300, 1000, 3000)):
    """What the late sweeps change (plain sweeps): over two sweeps after k, tcd's measure, the
    share of the change that moves bodies, dR.W.dR / dR.D.dR (D: the Delassus diagonal; 1 for
    a generic direction, 0 for a self-stress), the particles' velocity change (relative L1),
    and the change of the particles' resultant impulses relative to the resultants."""
    step.prepare()
    done = 0
    for k in marks:
        step.sweeps(k - done, 0)
        d0 = step.arrays()
        step.sweeps(2, 0)
        done = k + 2
        d1 = step.arrays()
        dr = d1["r"] - d0["r"]
        dv, dw = body_response(d0, dr)
        mass = 1.0 / d0["im"]
        inertia = np.where(d0["ii"] > 0, 1.0 / np.maximum(d0["ii"], 1e-300), 0.0)
        moved = (mass[:, None] * dv**2).sum() + (inertia[:, None] * dw**2).sum()
        nrm = d0["nrm"]
        wnn, wtt = delassus_diagonal(d0)
        drn = (dr * nrm).sum(1)
        diag = (wnn * drn**2 + wtt * ((dr - drn[:, None] * nrm) ** 2).sum(1)).sum()
        f0, t0 = resultants(d0)
        f1, t1 = resultants(d1)
        res = ((np.linalg.norm(f1 - f0, axis=1) + np.linalg.norm(t1 - t0, axis=1)).sum()
               / (np.linalg.norm(f1, axis=1) + np.linalg.norm(t1, axis=1)).sum())
        print(f"after {k} sweeps, over 2: impulses {np.abs(dr).sum() / np.abs(d1['r']).sum():.2e}, "
              f"dR.W.dR / dR.D.dR {moved / diag:.2e}, velocities "
              f"{np.abs(d1['v'] - d0['v']).sum() / np.abs(d0['v']).sum():.2e}, resultants {res:.2e}",
              flush=True)


def parse(text):
    out = []
    for item in text.split(","):
        kind, k = item.split(":")
        if kind not in ("plain", "nncg"):
            raise SystemExit(f"{item}: expected plain:K or nncg:K")
        out.append((kind, int(k)))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--state", default="/tmp/tcd_pour_state.pkl")
    ap.add_argument("--time", type=float, default=0.48)
    ap.add_argument("--references", default="plain:100000,nncg:100000")
    ap.add_argument("--sweeps", default="nncg:0,nncg:300,nncg:1138,plain:1832,plain:30000")
    ap.add_argument("--drift", action="store_true", help="what the late sweeps change, then stop")
    a = ap.parse_args()
    tcd.init("cpu", "f64")
    step = Step(solver_convergence.pour_state(2600, a.time, a.state), a.time, False)
    if a.drift:
        drift(step)
        return

    def solve(kind, k):
        step.prepare()
        res = step.sweeps(k, 1 if kind == "nncg" else 0) if k else float("nan")
        d = step.arrays()
        return res, d["r"], d["v"]

    refs = {}
    for kind, k in parse(a.references):
        refs[(kind, k)] = solve(kind, k)
        print(f"reference {kind} {k} sweeps: measure {refs[(kind, k)][0]:.2e}", flush=True)
    rows = list(refs.items()) + [((kind, k), solve(kind, k)) for kind, k in parse(a.sweeps)]
    print("| solve | measure | " + " | ".join(f"impulses, velocities vs {kk} {n}" for kk, n in refs) + " |")
    for (kind, k), (res, r, v) in rows:
        cells = [f"{np.abs(r - rr).sum() / np.abs(rr).sum():.2e}, {np.abs(v - rv).sum() / np.abs(rv).sum():.2e}"
                 for _, rr, rv in refs.values()]
        print(f"| {kind} {k} | {res:.2e} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
