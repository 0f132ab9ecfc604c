"""Active-set Krylov corrections between Gauss-Seidel sweeps on the pour's impact step: a
prototype in NumPy, not part of tcd (session 26).

Same state and driver as `coarse_correction.py`. Between blocks of plain symmetric sweeps the
contact statuses are frozen (open: R_n = 0; sliding: R_n > 0 and |R_t| = mu R_n; sticking: the
rest) and the linear problem they define is solved by preconditioned conjugate gradients,
matrix-free (W x = H M^-1 H^T x): for the sticking contacts the whole relative velocity
u + g n/(theta H) vanishes, for the sliding ones its normal part (their tangential impulse is
held), the open ones take no change. Then R is projected on the cones and the velocities
updated by M^-1 H^T dR, and Gauss-Seidel goes on. One CG iteration (a product by W) costs about
one sweep.

`--mode cg` holds the sliding contacts' tangential impulses and solves the symmetric system by
Jacobi-preconditioned CG; `--mode gmres` lets them follow the cone (trial direction
n + mu t_hat, R_t = mu R_n t_hat, test direction n) and solves the nonsymmetric system by
GMRES(k) from zero, right-preconditioned by the contacts' diagonal Delassus blocks.

    python benchmarks/krylov_correction.py [--mode cg|gmres] [--block 20] [--cg 0,10,20]
        [--sweeps 300] [--frictionless] [--nncg]

Session 26 (this 2-core CPU, f64; residual = tcd's measure after the block's last sweep;
"work" = sweeps + Krylov iterations, one product by W costing about one sweep):
  - frictionless, cg 20 per block of 20: 3.29e-5 after 80 sweeps (140 work), 1.6e-10 after 200
    (plain: 5.16e-3 and 1.75e-3): with frozen statuses that hold, Krylov solves the LCP.
  - friction 0.7, cg (sliding tangential held): 20 per block 5.14e-4 at 200 sweeps (380 work)
    against 6.05e-4 plain; 100 or 300 iterations make it worse (3.3e-3, 1.4e-2).
  - friction 0.7, gmres, plain symmetric sweeps: 1e-4 after about 1000 work (gmres 40 per
    block of 40: 1.13e-4 at 920, 8.87e-5 at 1080), against about 1830 plain sweeps (1.73e-4
    at 1200); gmres 10 per block of 10 or 20 stalls at 1.4e-4.
  - the same with NNCG sweeps (`--nncg`, the shipped default): 1e-4
    after about 850 work (gmres 40 / block 40) or 940 (gmres 20 / block 40), against about
    1300 for NNCG alone (1.17e-4 at 1200): 1.3-1.5 times fewer passes.
  Each correction changes the impulses by 0.2-9 % (sum |dR| / sum |R|) and flips 6-147
  contacts' statuses; the next sweep's change is back at 2e-4-1e-3. Issue 2 needs about 3
  times fewer passes on these steps, and GMRES(40) would keep 40 extra vectors per contact
  (about 2.6 KB per particle, over issue 8's 2 KB), so this is not built into tcd.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import tcd  # noqa: E402
import solver_convergence  # noqa: E402
from coarse_correction import (Step, body_response, delassus_diagonal, relative_velocity,  # noqa: E402
                               velocity_jump)


def gmres(aop, b, iters):
    """GMRES(iters) from zero on aop(y) = b (arrays of any shape, Euclidean products)."""
    beta = np.sqrt((b * b).sum())
    vs, hh = [b / beta], np.zeros((iters + 1, iters))
    for k in range(iters):
        w = aop(vs[k])
        for l in range(k + 1):
            hh[l, k] = (w * vs[l]).sum()
            w = w - hh[l, k] * vs[l]
        hh[k + 1, k] = np.sqrt((w * w).sum())
        vs.append(w / max(hh[k + 1, k], 1e-300))
    e1 = np.zeros(iters + 1)
    e1[0] = beta
    return sum(c * v for c, v in zip(np.linalg.lstsq(hh, e1, rcond=None)[0], vs[:iters]))


def statuses(d, slack=1e-9):
    nrm, r = d["nrm"], d["r"]
    rn = (r * nrm).sum(1)
    rt = r - rn[:, None] * nrm
    active = rn > 0
    slide = active & (np.linalg.norm(rt, axis=1) >= d["mu"] * rn * (1 - slack))
    return active, slide


def project(d, r):
    nrm = d["nrm"]
    rn = np.maximum((r * nrm).sum(1), 0.0)
    tang = r - (r * nrm).sum(1)[:, None] * nrm
    nt, limit = np.linalg.norm(tang, axis=1), d["mu"] * rn
    scale = np.where(nt > limit, limit / np.maximum(nt, 1e-300), 1.0)
    return rn[:, None] * nrm + scale[:, None] * tang


def correction(d, iters, mode="cg"):
    nrm = d["nrm"]
    active, slide = statuses(d)
    stick = active & ~slide

    def proj(x):                          # onto the frozen statuses' free directions
        out = np.zeros_like(x)
        out[stick] = x[stick]
        xn = (x * nrm).sum(1)
        out[slide] = (xn[:, None] * nrm)[slide]
        return out

    def op(x):
        return proj(velocity_jump(d, *body_response(d, x)))

    wnn, wtt = delassus_diagonal(d)

    def prec(x):
        xn = (x * nrm).sum(1)
        return (xn / wnn)[:, None] * nrm + (x - xn[:, None] * nrm) / wtt[:, None]

    u = relative_velocity(d)
    g = proj(u + d["rhs"][:, None] * nrm)
    if mode == "gmres":
        rn = (d["r"] * nrm).sum(1)
        rt = d["r"] - rn[:, None] * nrm
        that = rt / np.maximum(np.linalg.norm(rt, axis=1), 1e-300)[:, None]
        lift = np.where(slide[:, None], d["mu"][:, None] * that, 0.0)

        def trial(x):                     # sliding: R_t = mu R_n t_hat moves with R_n
            return x + (x * nrm).sum(1)[:, None] * lift

        def aop(y):                       # right-preconditioned operator
            return proj(velocity_jump(d, *body_response(d, trial(proj(prec(y))))))

        y = gmres(aop, -g, iters)
        return project(d, d["r"] + trial(proj(prec(y))))
    x = np.zeros_like(g)
    res = -g
    z = proj(prec(res))
    p = z.copy()
    rz = (res * z).sum()
    for _ in range(iters):
        q = op(p)
        alpha = rz / max((p * q).sum(), 1e-300)
        x += alpha * p
        res -= alpha * q
        z = proj(prec(res))
        rz_new = (res * z).sum()
        p = z + (rz_new / rz) * p
        rz = rz_new
    return project(d, d["r"] + x)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--state", default="/tmp/tcd_pour_state.pkl")
    ap.add_argument("--time", type=float, default=0.48)
    ap.add_argument("--block", type=int, default=20)
    ap.add_argument("--cg", default="0,10,20,50")
    ap.add_argument("--sweeps", type=int, default=300)
    ap.add_argument("--frictionless", action="store_true")
    ap.add_argument("--mode", default="cg", choices=("cg", "gmres"))
    ap.add_argument("--nncg", action="store_true", help="NNCG sweeps instead of plain ones")
    a = ap.parse_args()
    tcd.init("cpu", "f64")
    step = Step(solver_convergence.pour_state(2600, a.time, a.state), a.time, a.frictionless)
    for iters in [int(s) for s in a.cg.split(",")]:
        t0 = time.perf_counter()
        step.prepare()
        done, work, line = 0, 0, []
        while done < a.sweeps:
            k = min(a.block, a.sweeps - done)
            residual = step.sweeps(k, 1 if a.nncg else 0)
            done += k
            work += k
            line.append(f"{done}/{work}:{residual:.2e}")
            if iters and done < a.sweeps:
                d = step.arrays()
                step.write_back(d, correction(d, iters, a.mode))
                work += iters
        print(f"cg {iters} ({time.perf_counter() - t0:.0f} s) sweeps/work:residual " + " ".join(line[1::2]), flush=True)


if __name__ == "__main__":
    main()
