"""Active-set Krylov corrections between Gauss-Seidel sweeps on a step of the bonded shear: a
prototype in NumPy, not part of tcd (session 26). See `krylov_correction.py` for the pour.

The shipped seed-1 sample is sheared as `tcd bench shear` plans it (serial, tolerance 1e-4),
`--steps` steps are taken, then the next step is solved again and again from its warm start:
blocks of sweeps of `solver.nlgs_serial` (particle-block bond relaxation, symmetric or forward,
plain or NNCG) and, between blocks, GMRES on the linear problem of the frozen statuses: intact
bonds bilateral with their compliance ((W + C) dR = -(u + C R + rhs)), sticking contacts
u + g n = 0, sliding contacts along n + mu t_hat tested on n, open contacts unchanged.

    python benchmarks/krylov_shear.py [--steps 200] [--gmres 0,10,20] [--block 5] [--sweeps 60]
        [--forward] [--nncg]

Session 26 (this 2-core CPU, f64; `--steps 100 --nncg`: step 101 took 20 sweeps to 9.54e-5
as run, 3438 contacts, 12829 bonds at the bench's 0.01 mm gap). Each call of the sweep kernel
restarts NNCG's momentum, so blocks of 5 reach 1e-4 only after 50 sweeps, blocks of 10 after
about 35. Residual (tcd's measure) at the block ends, "sweeps/work":
  - blocks of 5: no correction 1.73e-4 at 10/10, 9.90e-5 at 50/50; GMRES 10 per block
    1.91e-4 at 10/20, 9.59e-5 at 40/110; GMRES 20 9.38e-5 at 45/205.
  - blocks of 10: no correction 1.23e-4 at 20/20; GMRES 40 9.94e-5 at 20/60, 5.59e-5 at 40/160.
  GMRES itself hardly converges on the bonded system: its relative residual after 10 / 40 /
  100 iterations (diagonal-block preconditioner) is 0.51 / 0.48 / 0.28. The stiff bonds
  between grains of masses 1 to 512 make W + C ill-conditioned; the particle-block relaxation
  solves each grain's star of bonds exactly and gets to 1e-4 in 20 sweeps from the warm
  start. No gain; not built into tcd.
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
from tcd import solver as sk  # noqa: E402
from tcd.state import get  # noqa: E402
from krylov_correction import gmres, project, statuses  # noqa: E402
from coarse_correction import (body_response, contact_arrays, delassus_diagonal,  # noqa: E402
                               relative_velocity, velocity_jump, write_rows)
from solver_convergence import begin_step  # noqa: E402


def setup(sample, tolerance):
    from tcd.config import parse_scenario
    from tcd.runner import plan_shears
    scn = parse_scenario(f'name = "k"\nseeds = [1]\n[solver]\ntolerance = {tolerance!r}\n'
                         f'schedule = "serial"\n[[stage]]\nkind = "shear"\n'
                         f'sample = {str(Path(sample).resolve())!r}\n', "<krylov shear>")
    sims, _ = plan_shears(scn, scn.stages[0], [1], [Path(sample)])
    return sims[0]


def arrays(sim):
    """`coarse_correction.contact_arrays`, and the bonds' arrays."""
    bd = sim.bonds
    nb = int(bd.total[None])
    b = dict(i=get(bd.i, nb), j=get(bd.j, nb), nrm=get(bd.normal, nb), r=get(bd.impulse, nb),
             cn=get(bd.cn, nb), ct=get(bd.ct, nb), rhs_n=get(bd.rhs_n, nb),
             rhs_t=get(bd.rhs_t, nb), state=get(bd.state, nb))
    return contact_arrays(sim), b


def as_items(d, b, intact):
    """The bonds appended to the contacts (same H); returns the joint item arrays."""
    e = dict(d)
    for k in ("i", "j", "nrm", "r"):
        e[k] = np.concatenate([d[k], b[k][intact]])
    return e


def correction(sim, iters):
    d, b = arrays(sim)
    m = len(d["i"])
    intact = b["state"] == 0
    e = as_items(d, b, intact)
    nrm = e["nrm"]
    active, slide = statuses(d)
    stick = active & ~slide
    bn, bt = b["cn"][intact], b["ct"][intact]

    def proj(x):
        out = np.zeros_like(x)
        out[m:] = x[m:]
        out[:m][stick] = x[:m][stick]
        xn = (x[:m] * nrm[:m]).sum(1)
        out[:m][slide] = (xn[:, None] * nrm[:m])[slide]
        return out

    def compliance(x):
        xb = x[m:]
        xn = (xb * nrm[m:]).sum(1)
        out = np.zeros_like(x)
        out[m:] = bn[:, None] * xn[:, None] * nrm[m:] + bt[:, None] * (xb - xn[:, None] * nrm[m:])
        return out

    wnn, wtt = delassus_diagonal(e)
    wnn[m:] += bn
    wtt[m:] += bt

    def prec(x):
        xn = (x * nrm).sum(1)
        return (xn / wnn)[:, None] * nrm + (x - xn[:, None] * nrm) / wtt[:, None]

    rn = (d["r"] * d["nrm"]).sum(1)
    rt = d["r"] - rn[:, None] * d["nrm"]
    that = rt / np.maximum(np.linalg.norm(rt, axis=1), 1e-300)[:, None]
    lift = np.zeros_like(nrm)
    lift[:m] = np.where(slide[:, None], d["mu"][:, None] * that, 0.0)

    def trial(x):
        return x + (x * nrm).sum(1)[:, None] * lift

    def aop(y):
        x = trial(proj(prec(y)))
        return proj(velocity_jump(e, *body_response(e, x)) + compliance(x))

    u = relative_velocity(e)
    g = u + compliance(e["r"])
    g[:m] += d["rhs"][:, None] * nrm[:m]
    g[m:] += b["rhs_n"][intact][:, None] * nrm[m:] + b["rhs_t"][intact]
    g = proj(g)
    y = gmres(aop, -g, iters)
    dx = trial(proj(prec(y)))
    rc = project(d, d["r"] + dx[:m])
    dr = np.concatenate([rc - d["r"], dx[m:]])
    dv, dw = body_response(e, dr)
    ct, p, bd = sim.contacts, sim.particles, sim.bonds
    rb = b["r"].copy()
    rb[intact] += dx[m:]
    for field, rows in ((bd.impulse, rb), (ct.impulse, rc), (p.v, d["v"] + dv), (p.w, d["w"] + dw)):
        write_rows(field, rows)
    return np.abs(dr).sum() / max(np.abs(e["r"]).sum(), 1e-300)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sample", default="samples/leutner_seed1_prepared.h5")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--gmres", default="0,10,20")
    ap.add_argument("--block", type=int, default=5)
    ap.add_argument("--sweeps", type=int, default=60)
    ap.add_argument("--forward", action="store_true")
    ap.add_argument("--nncg", action="store_true")
    a = ap.parse_args()
    tcd.init("cpu", "f64")
    sim = setup(a.sample, 1e-4)
    for _ in range(a.steps):
        sim.step()
    state, t = sim.state_dict(), sim.time
    sim.step()
    print(f"step {a.steps + 1} as run: {sim.last.sweeps} sweeps, residual {sim.last.residual:.2e}, "
          f"{sim.last.contacts} contacts", flush=True)
    p, wl, bd = sim.particles, sim.wall_fields, sim.bonds
    for iters in [int(s) for s in a.gmres.split(",")]:
        ct = begin_step(sim, state, t)
        sk.apply_warm_start(p, ct, bd)
        done, work, line, t0 = 0, 0, [], time.perf_counter()
        while done < a.sweeps:
            sk.nlgs_serial(p, wl, ct, bd, sim.stats, a.block, 1e-300, 1, 0 if a.forward else 1,
                           1 if a.nncg else 0, 1, 0)
            done += a.block
            work += a.block
            line.append(f"{done}/{work}:{float(sim.stats.residual[None]):.2e}")
            if iters and done < a.sweeps:
                correction(sim, iters)
                work += iters
        print(f"gmres {iters} ({time.perf_counter() - t0:.0f} s) " + " ".join(line), flush=True)


if __name__ == "__main__":
    main()
