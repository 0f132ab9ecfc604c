"""Solver variants tried on the pour's impact step and not kept (session 14), kept runnable.

The state is the one of `solver_convergence.py` (2600 binder spheres of `tcd bench pour` at
t = 0.48 s, 6486 contacts; poured once, about 2-4 min, and cached in a pickle). The SAME step
is solved to the same stopping rule as the solver's (sum |dR| / sum |R| of a full sweep below
the tolerance, 1e-4), cap 5000 or 20000 sweeps, by:
  - the shipped serial NNCG and plain symmetric Gauss-Seidel (references);
  - "selective": Gauss-Seidel that visits, between full sweeps every F sweeps, only the
    contacts touching a body that changed in this or the previous sweep by more than
    c x tol x mean |R| (the residual is only ever measured on full sweeps, so the stopping rule
    is the solver's own);
  - "anderson": Anderson acceleration of depth m on the map "one forward + one backward
    sweep", the mixed impulses projected on the friction cones and the bodies updated to
    them, restarted when a step makes the residual grow by more than `safe` times.
Updates/M counts contact updates per contact (the work), sweeps counts full and partial ones.

    python benchmarks/solver_experiments.py [--state /tmp/tcd_pour_state.pkl] [--only selective|anderson]

Session 14 (this 2-core CPU, f64): NNCG 1138 sweeps (0.262 s), plain 1832 (0.331 s);
selective: 1648-2660 updates per contact for F = 5..20 and c = 0.1..1 (0.34-0.52 s), against
1832 for plain sweeps: the hot set is nearly every contact (a change anywhere in the packing
reaches every body through its neighbours within a sweep or two); anderson: m = 2, 5, 8 never
reached 1e-4 within 5000 sweeps (residual 1.3e-4 to 4.4e-4 at the cap), with or without
restarts: the projections on the friction cones break the fixed-point map's smoothness that
Anderson mixing relies on.
"""

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import taichi as ti

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout
sys.path.insert(0, str(Path(__file__).resolve().parent))
import tcd  # noqa: E402
import tcd.simulation as simulation  # noqa: E402
from tcd import bench  # noqa: E402
from tcd import solver as sk  # noqa: E402
from solver_convergence import pour_state  # noqa: E402

MMAX = 8        # deepest Anderson history


@ti.kernel
def nlgs_selective(p: ti.template(), wl: ti.template(), ct: ti.template(), st: ti.template(),
                   hot: ti.template(), max_sweeps: ti.i32, tol: float, full_every: ti.i32,
                   c_thr: float) -> ti.i64:
    updates = ti.i64(0)
    ti.loop_config(serialize=True)
    for _ in range(1):
        M = ct.total[None]
        n = p.count[None]
        for q in range(n):
            hot[q] = -10
        sweeps = 0
        residual = 0.0
        done = 0
        thr = 0.0
        while done == 0:
            full = 0
            if sweeps % full_every == 0 or sweeps + 1 >= max_sweeps:
                full = 1
            dsum = 0.0
            rsum = 0.0
            for kk in range(M):
                k = kk
                if sweeps % 2 == 1:
                    k = M - 1 - kk
                i, j = ct.i[k], ct.j[k]
                visit = full
                if visit == 0:
                    if hot[i] >= sweeps - 1:
                        visit = 1
                    elif j < n:
                        if hot[j] >= sweeps - 1:
                            visit = 1
                if visit == 1:
                    dr, r_new = sk.solve_contact_dr(p, wl, ct, k, n)
                    updates += 1
                    a = dr.norm()
                    if a > thr:
                        hot[i] = sweeps
                        if j < n:
                            hot[j] = sweeps
                    if full == 1:
                        dsum += a
                        rsum += r_new.norm()
            sweeps += 1
            if full == 1:
                residual = 0.0
                if rsum > 0.0:
                    residual = dsum / rsum
                thr = c_thr * tol * rsum / ti.max(M, 1)
                if residual <= tol or sweeps >= max_sweeps:
                    done = 1
        st.sweeps[None] = sweeps
        st.residual[None] = residual
    return updates


@ti.func
def project_cone(r, n, mu):
    rn = ti.max(r.dot(n), 0.0)
    rt = r - r.dot(n) * n
    nt2 = rt.norm_sqr()
    lim = mu * rn
    if nt2 > lim * lim:
        s = 0.0
        if nt2 > 0.0:
            s = lim / ti.sqrt(nt2)
        rt *= s
    return rn * n + rt


@ti.kernel
def nlgs_anderson(p: ti.template(), wl: ti.template(), ct: ti.template(), st: ti.template(),
                  x0: ti.template(), fprev: ti.template(), gprev: ti.template(),
                  dF: ti.template(), dG: ti.template(), gram: ti.template(), rhs: ti.template(),
                  gam: ti.template(), max_sweeps: ti.i32, tol: float, m: ti.i32, reg: float,
                  safe: float) -> ti.i64:
    updates = ti.i64(0)
    ti.loop_config(serialize=True)
    for _ in range(1):
        M = ct.total[None]
        n = p.count[None]
        sweeps = 0
        residual = 0.0
        done = 0
        it = 0
        fn_prev = 0.0
        while done == 0:
            for k in range(M):
                x0[k] = ct.impulse[k]
            dsum = 0.0
            rsum = 0.0
            for ps in range(2):              # the map: a forward then a backward sweep
                for kk in range(M):
                    k = kk
                    if ps == 1:
                        k = M - 1 - kk
                    dr, r_new = sk.solve_contact_dr(p, wl, ct, k, n)
                    updates += 1
                    if ps == 1:
                        dsum += dr.norm()
                        rsum += r_new.norm()
                sweeps += 1
            residual = 0.0
            if rsum > 0.0:
                residual = dsum / rsum
            if residual <= tol or sweeps >= max_sweeps:
                done = 1
            if done == 0 and m > 0:
                fn = 0.0
                for k in range(M):
                    fn += (ct.impulse[k] - x0[k]).norm_sqr()
                if it >= 2 and fn > safe * fn_prev:
                    it = 0                   # restart
                col = (it - 1) % m
                mm = ti.min(it, m)
                if it >= 1:
                    for k in range(M):
                        dF[col, k] = ct.impulse[k] - x0[k] - fprev[k]
                        dG[col, k] = ct.impulse[k] - gprev[k]
                    for a in range(mm):
                        s = 0.0
                        for k in range(M):
                            s += dF[a, k].dot(dF[col, k])
                        gram[a, col] = s
                        gram[col, a] = s
                for k in range(M):
                    fprev[k] = ct.impulse[k] - x0[k]
                    gprev[k] = ct.impulse[k]
                if it >= 1:
                    for a in range(mm):
                        s = 0.0
                        for k in range(M):
                            s += dF[a, k].dot(fprev[k])
                        rhs[a] = s
                    tr = 0.0
                    for a in range(mm):
                        tr += gram[a, a]
                    for a in range(mm):              # (gram + reg tr I) gam = rhs
                        for b in range(mm):
                            gram[MMAX + a, b] = gram[a, b]
                        gram[MMAX + a, a] += reg * tr + 1e-300
                        gam[a] = rhs[a]
                    for c in range(mm):
                        for r_ in range(c + 1, mm):
                            fac = gram[MMAX + r_, c] / gram[MMAX + c, c]
                            for b in range(c, mm):
                                gram[MMAX + r_, b] -= fac * gram[MMAX + c, b]
                            gam[r_] -= fac * gam[c]
                    for cc in range(mm):
                        c = mm - 1 - cc
                        s = gam[c]
                        for b in range(c + 1, mm):
                            s -= gram[MMAX + c, b] * gam[b]
                        gam[c] = s / gram[MMAX + c, c]
                    for k in range(M):               # x = g - dG gam, projected, bodies updated
                        if ct.wnn[k] > 0.0:
                            x = ct.impulse[k]
                            for a in range(mm):
                                x -= gam[a] * dG[a, k]
                            x = project_cone(x, ct.normal[k], ct.mu[k])
                            sk.apply_impulse(p, ct.i[k], ct.j[k], ct.normal[k], x - ct.impulse[k])
                            ct.impulse[k] = x
                it += 1
                fn_prev = fn
        st.sweeps[None] = sweeps
        st.residual[None] = residual
    return updates


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--state", default="/tmp/tcd_pour_state.pkl")
    ap.add_argument("--only", choices=("selective", "anderson"))
    a = ap.parse_args()
    tcd.init("cpu", "f64")
    state = pour_state(2600, 0.48, a.state)
    sim = bench.pour_setup(2600, 1, 1e-4)
    cap, pcap = sim.contacts.capacity, sim.particles.capacity
    real = tcd.backend.real()
    hot = ti.field(ti.i32, shape=pcap)
    vec = lambda *shape: ti.Vector.field(3, real, shape=shape)   # noqa: E731
    x0, fprev, gprev, dF, dG = vec(cap), vec(cap), vec(cap), vec(MMAX, cap), vec(MMAX, cap)
    gram = ti.field(real, shape=(2 * MMAX, MMAX))
    rhs, gam = ti.field(real, shape=MMAX), ti.field(real, shape=MMAX)
    shipped = sk.nlgs_serial
    variant = {}

    def solve(p, wl, ct, bd, st, max_sweeps, tol, check_every, accel, blocks):
        kind = variant.get("kind")
        if kind == "selective":
            variant["updates"] = nlgs_selective(p, wl, ct, st, hot, max_sweeps, tol,
                                                variant["full"], variant["c"])
        elif kind == "anderson":
            variant["updates"] = nlgs_anderson(p, wl, ct, st, x0, fprev, gprev, dF, dG, gram,
                                               rhs, gam, max_sweeps, tol, variant["m"], 1e-8,
                                               variant["safe"])
        else:
            variant["updates"] = None
            shipped(p, wl, ct, bd, st, max_sweeps, tol, check_every, accel, blocks)
    simulation.sk.nlgs_serial = solve
    runs = [("NNCG (shipped)", {}, "nncg", 20000), ("plain GS (shipped)", {}, "none", 20000)]
    if a.only != "anderson":
        runs += [(f"selective F={f} c={c}", {"kind": "selective", "full": f, "c": c}, "none", 20000)
                 for f in (5, 10, 20) for c in (0.1, 0.3, 1.0)]
    if a.only != "selective":
        runs += [(f"anderson m={m} safe={s}", {"kind": "anderson", "m": m, "safe": s}, "none", 5000)
                 for m in (2, 5, 8) for s in (1e30, 1.0, 2.0)]
    print("| variant | sweeps | residual | updates per contact | wall s |")
    print("|---|---|---|---|---|")
    for name, opts, acc, cap_sweeps in runs:
        variant.clear()
        variant.update(opts)
        sim.settings = dataclasses.replace(sim.settings, max_sweeps=cap_sweeps, tolerance=1e-4,
                                           acceleration=acc, schedule="serial")
        sim.schedule = "serial"
        for _ in range(2):                   # the first solve compiles
            sim.load_state_dict(state)
            sim.time = 0.48
            t0 = time.perf_counter()
            rec = sim.step()
            wall = time.perf_counter() - t0
        updates = variant["updates"] if variant.get("updates") is not None else rec.sweeps * rec.contacts
        print(f"| {name} | {rec.sweeps} | {rec.residual:.2e} | {updates / rec.contacts:.0f} | "
              f"{wall:.3f} |", flush=True)
    simulation.sk.nlgs_serial = shipped
    sim.close()


if __name__ == "__main__":
    main()
