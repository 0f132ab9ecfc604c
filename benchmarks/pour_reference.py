"""How far the pour's impact step is from long-run solutions when the solver stops: a check of
what tcd's measure at 1e-4 means there (session 26).

The state of `solver_convergence.py` (2600 spheres of `tcd bench pour` at t = 0.48 s) is
solved from the same warm start by `solver.nlgs_serial` (symmetric sweeps, plain or NNCG) for
k sweeps, and compared with reference solves of many sweeps: relative L1 differences of the
contact impulses and of the particle velocities.

    python benchmarks/pour_reference.py [--references plain:100000,nncg:100000]
        [--sweeps nncg:1138,plain:1832,plain:30000]

Session 26 (this 2-core CPU, f64): the references stall, plain 1.71e-5 and NNCG 1.28e-5 after
100000 sweeps (plain 4.78e-5 after 30000), 11 % apart in impulses and 0.35 % in velocities.
The benchmark's stops (NNCG 1138 sweeps, measure 1.28e-4; plain 1832, 1.25e-4) are 33 % off
either in impulses and 1.0 % in velocities (warm start: 53 % and 4.6 %; 300 NNCG sweeps: 38 %
and 1.2 %). The forces of the rigid hyperstatic frictional bed are not unique; its velocities
settle to about 1 % long before the measure reaches 1e-4.
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
from coarse_correction import Step  # noqa: E402


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
    a = ap.parse_args()
    tcd.init("cpu", "f64")
    step = Step(solver_convergence.pour_state(2600, a.time, a.state), a.time, False)

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
