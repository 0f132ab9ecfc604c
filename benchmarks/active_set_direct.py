"""Active-set steps with a sparse direct solve between Gauss-Seidel sweeps, on a step of the
bonded shear: a prototype in NumPy and SciPy (SciPy is not a dependency of tcd; install it
beside, e.g. `pip install --target DIR scipy` and PYTHONPATH=DIR), not part of tcd (session 57).

The question: the study's shear step stopped at tolerance 1e-5 is about 2 % from its solution
in its impulses, and 1e-6 and 1e-7 cost a hundred and a thousand times the sweeps
(docs/results.md, "What the tolerance leaves in the grains' velocities"); GMRES on the frozen
statuses hardly converged (krylov_shear.py, session 26). Does an exact solve of the frozen
statuses' linear problem reach the converged step in a few solves?

The step: a run's checkpoint, `--settle-steps` steps at the settling tolerance (as
step_error.py), then the next step prepared as `Simulation._step` does (contacts, predictor,
bonds' terms, warm start), and a reference: the same step after `--reference-sweeps` sweeps
at tolerance 1e-13. Then `--rounds` rounds of:
  - `--sweeps` serial sweeps with the scenario's flags (symmetric, bond blocks, NNCG);
  - the contacts' statuses by the natural map, xi = R - (u + rhs n) / W_nn: open
    (xi_n <= 0), sticking (|xi_t| <= mu xi_n) or sliding (direction t = xi_t / |xi_t|);
  - the linear problem of these statuses, solved in the grains' velocities:
    (M + H^T G H) V = M v_free + H^T (R0 - G rhs), R = R0 - G (H V + rhs). Per item, G =
    P S^-1 Q^T on its free directions: an intact bond's compliance C^-1 (u + C R + rhs = 0);
    a sticking contact u + rhs n + eps W_nn (R - R_cur) = 0 (a proximal compliance: a rigid
    sticking set is statically indeterminate and its factor singular without it), a sliding
    one R = R_n (n + mu t) with n . (u + rhs n) + eps W_nn (R_n - R_n,cur) = 0; open
    contacts R = 0, broken bonds held. H has 3 rows per item and 6 columns per grain (the
    bonds' arms at the middle of their gap). SuperLU on K scaled to a unit diagonal, ordered on
    K + K^T, no pivoting: 35142 unknowns, 1.36 M entries, 19 M in the factors, 3.5-4 s;
  - R projected on the cones, `--damping` of the change taken (or `--line-search`, below),
    v = v + M^-1 H^T dR.
`--hold-contacts` solves the bonds alone exactly, the contacts' impulses held (a block
Gauss-Seidel: the bonded network exactly, the contacts by the sweeps).

    PYTHONPATH=<scipy> python benchmarks/active_set_direct.py CKPT SCENARIO [--settle-steps 20]
        [--time-step 2e-4] [--settle-tolerance 1e-5] [--sweeps 5] [--rounds 10]
        [--reference-sweeps 60000] [--eps 1e-6] [--damping 1 | --line-search] [--hold-contacts]

Session 57, the study's seed 1 at 1.0 mm (the state of step_error.py's table), 20 steps at
tolerance 1e-5, reference 20000 sweeps (2607 contacts, 17588 bonds, 16183 intact); "impulses"
is the relative 2-norm distance of all impulses to the reference's ("velocities" that of the
grains' velocities and spins together, where the small grains' spins weigh most). Sweeps alone: 1.98e-2
after 17 sweeps, 1.93e-2 after 100, 1.51e-2 after 1000.
  - `--hold-contacts`, 5 sweeps a round: the exact bond solve changes the impulses by 5.6e-4
    after the first 5 sweeps, then 6e-5 to 2e-5 a round; impulses 1.99e-2 -> 1.97e-2 after
    six rounds (30 sweeps). Given the contacts, the sweeps already have the bonded network
    nearly solved: what is slow is not the bonds' stiffness but the contacts and their
    coupling with the grains.
  - the whole active set, 5 sweeps a round: the first solve takes the impulses from 1.99e-2
    to 1.54e-2 (as far as 1000 sweeps), then every round makes it worse (8.8e-2 at the
    third, 1.4 at the eighth) and the sweeps' residual rises from 1e-5 to 1e-3-1e-2: about
    a tenth of the contacts change status each round, and the small grains' spins
    (inverse inertia up to 2.3e11) amplify every change. Damped steps (0.5, 0.2) diverge as
    well, more slowly.
  - `--line-search` (the largest of 1, 1/2, ... 1/64 of the change that lowers the summed
    squared natural-map residual of all items): no fraction of the solve's change lowers it,
    in any of eight rounds (merit 8.8e-10 after 5 sweeps, 2.0e-10 after 40, all by the
    sweeps): the frozen statuses' solve, regularised, is not a descent direction here.
  So a Newton method on this problem would need the generalised Jacobian of the natural map
  itself (LMGC90's nonsmooth Newton solvers), not a solve of frozen statuses; the bond block
  alone gives nothing. Not built into tcd.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout
sys.path.insert(0, str(Path(__file__).resolve().parent))            # the other prototypes


EPS = 1e-6
PERMC = "MMD_AT_PLUS_A"
HOLD_CONTACTS = False
DAMPING = 1.0
LINE_SEARCH = False


def cross_matrix(n):
    """[n]x for each row of n: (k, 3, 3)."""
    z = np.zeros(len(n))
    return np.stack([np.stack([z, -n[:, 2], n[:, 1]], 1),
                     np.stack([n[:, 2], z, -n[:, 0]], 1),
                     np.stack([-n[:, 1], n[:, 0], z], 1)], 1)


def read(sim):
    """The contacts (c), the bonds (b) and the grains (g) as arrays: those of the other
    prototypes (`krylov_shear.arrays`), and the bonds' half gaps (their arms)."""
    from tcd.state import get
    from krylov_shear import arrays
    d, b = arrays(sim)
    c = {k: d[k] for k in ("i", "j", "nrm", "r", "rhs", "mu")}
    b["hg"] = get(sim.bonds.half_gap, len(b["i"]))
    g = {k: d[k] for k in ("v", "w", "rad", "im", "ii", "wallv")}
    g["n"] = sim.n
    return c, b, g


def write(sim, c, b, g):
    from coarse_correction import write_rows
    for field, rows in ((sim.contacts.impulse, c["r"]), (sim.bonds.impulse, b["r"]),
                        (sim.particles.v, g["v"]), (sim.particles.w, g["w"])):
        write_rows(field, rows)


def operator(c, b, g):
    """H (3 rows per item: the contacts, then the bonds; 6 columns per grain, v then w), the
    items' normals, and the arrays the equations need."""
    import scipy.sparse as sp
    n = g["n"]
    i = np.concatenate([c["i"], b["i"]])
    j = np.concatenate([c["j"], b["j"]])
    nrm = np.concatenate([c["nrm"], b["nrm"]])
    ai = np.concatenate([g["rad"][c["i"]], g["rad"][b["i"]] + b["hg"]])
    part = j < n
    jj = np.where(part, j, 0)
    aj = np.concatenate([np.where(c["j"] < n, g["rad"][np.where(c["j"] < n, c["j"], 0)], 0.0),
                         g["rad"][b["j"]] + b["hg"]])
    k = len(i)
    nx = cross_matrix(nrm)
    eye = np.broadcast_to(np.eye(3), (k, 3, 3))
    rows, cols, vals = [], [], []

    def block(mask, col0, mat):
        kk = np.nonzero(mask)[0]
        r = (3 * kk[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2)
        cc = (col0[kk][:, None, None] + np.arange(3)[None, None, :]).repeat(3, 1)
        rows.append(r.ravel())
        cols.append(cc.ravel())
        vals.append(mat[kk].ravel())

    allk = np.ones(k, bool)
    block(allk, 6 * i, -eye)
    block(allk, 6 * i + 3, ai[:, None, None] * nx)
    block(part, 6 * jj, eye)
    block(part, 6 * jj + 3, aj[:, None, None] * nx)
    h = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(3 * k, 6 * n))
    minv = np.repeat(np.stack([g["im"], g["ii"]], 1), 3, 1).ravel()
    # the relative velocities now: H v, and the walls' side
    vel = np.concatenate([g["v"], g["w"]], 1).ravel()
    u = (h @ vel).reshape(k, 3)
    wall = ~part
    u[wall] += g["wallv"][j[wall] - n]
    return h, minv, nrm, u, k


def direct_round(sim, c, b, g, stats):
    """One active-set solve of the step's problem from the current impulses, in the grains'
    velocities: (M + H^T G H) V = M v_free + H^T (R0 - G rhs) with G = P S^-1 Q^T per item (S = Q^T C P
    its compliance on its free directions: the bonds' C, eps W_nn for the contacts), then
    R = R0 - G (H V + rhs), projected on the cones. Writes the new impulses and velocities into
    `sim`."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl
    t0 = time.perf_counter()
    h, minv, nrm, u, k = operator(c, b, g)
    n = g["n"]
    mc = len(c["i"])
    intact = b["state"] == 0
    r = np.concatenate([c["r"], b["r"]])
    rhs = np.concatenate([c["rhs"][:, None] * c["nrm"], b["rhs_n"][:, None] * b["nrm"] + b["rhs_t"]])
    jw = np.concatenate([c["j"], b["j"]])
    wall = jw >= n
    rhs_w = rhs.copy()                   # the walls' side of H V goes with the right side
    rhs_w[wall] += g["wallv"][jw[wall] - n]
    part = c["j"] < n
    w_diag_n = g["im"][c["i"]] + np.where(part, g["im"][np.where(part, c["j"], 0)], 0.0)
    # statuses (the natural map)
    uc = u[:mc] + rhs[:mc]
    xi = c["r"] - uc / w_diag_n[:, None]
    xin = (xi * c["nrm"]).sum(1)
    xit = xi - xin[:, None] * c["nrm"]
    xit_norm = np.linalg.norm(xit, axis=1)
    open_ = xin <= 0
    stick = ~open_ & (xit_norm <= c["mu"] * xin)
    slide = ~open_ & ~stick
    that = xit / np.maximum(xit_norm, 1e-300)[:, None]
    if HOLD_CONTACTS:                    # block Gauss-Seidel: the bonds solved exactly, the
        stick[:] = slide[:] = False      # contacts' impulses held (the sweeps move them)
    G = np.zeros((k, 3, 3))
    cn_ = c["nrm"]
    eps = EPS * w_diag_n
    G[:mc][stick] = np.eye(3) / eps[stick][:, None, None]
    d = cn_ + c["mu"][:, None] * that
    G[:mc][slide] = (d[:, :, None] * cn_[:, None, :] / eps[:, None, None])[slide]
    bn = b["nrm"]
    nn = bn[:, :, None] * bn[:, None, :]
    safe = np.where(intact, 1.0, 0.0)
    G[mc:] = safe[:, None, None] * (nn / np.where(intact, b["cn"], 1.0)[:, None, None]
                                    + (np.eye(3) - nn) / np.where(intact, b["ct"], 1.0)[:, None, None])
    kk = np.arange(k)
    rr = (3 * kk[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2)
    cc = (3 * kk[:, None, None] + np.arange(3)[None, None, :]).repeat(3, 1)
    Gm = sp.csr_matrix((G.ravel(), (rr.ravel(), cc.ravel())), shape=(3 * k, 3 * k))
    vel = np.concatenate([g["v"], g["w"]], 1).ravel()
    v_free = vel - minv * (h.T @ r.ravel())
    K = (sp.diags(1.0 / minv) + h.T @ Gm @ h).tocsc()
    # the contacts' regularisation acts on the change of their impulses (a proximal term,
    # u + rhs n + eps W_nn (R - R_cur) = 0): R = R0 - G (H V + rhs), R0 the current impulses
    # on the free directions (sticking: R_cur; sliding: d (n . R_cur); bonds and open: 0)
    r0 = np.zeros((k, 3))
    r0[:mc][stick] = c["r"][stick]
    r0[:mc][slide] = (d * (c["r"] * cn_).sum(1)[:, None])[slide]
    if HOLD_CONTACTS:
        r0[:mc] = c["r"]
    r0[mc:][~intact] = b["r"][~intact]  # a broken bond's impulse, if any, is held
    f = v_free / minv + h.T @ (r0.ravel() - Gm @ rhs_w.ravel())
    t1 = time.perf_counter()
    # scaled to a unit diagonal, ordered on the pattern of K + K^T, no pivoting (3.5 s and 19 M
    # entries in the factors, where SuperLU's partial pivoting fills in far more)
    dd = 1.0 / np.sqrt(np.abs(K.diagonal()))
    D = sp.diags(dd)
    lu = spl.splu((D @ K @ D).tocsc(), permc_spec=PERMC, diag_pivot_thresh=0.0,
                  options=dict(SymmetricMode=True))
    V = dd * lu.solve(dd * f)
    t2 = time.perf_counter()
    rnew = r0 - (Gm @ (h @ V + rhs_w.ravel())).reshape(k, 3)
    # project the contacts on their cones
    rc = rnew[:mc]
    rn = np.maximum((rc * cn_).sum(1), 0.0)
    rt = rc - (rc * cn_).sum(1)[:, None] * cn_
    tn = np.linalg.norm(rt, axis=1)
    scale = np.where(tn > c["mu"] * rn, c["mu"] * rn / np.maximum(tn, 1e-300), 1.0)
    if not HOLD_CONTACTS:
        rnew[:mc] = rn[:, None] * cn_ + scale[:, None] * rt
    if LINE_SEARCH:                      # the largest of 1, 1/2, ... 1/64 that lowers the merit
        vel0 = vel
        phi0 = merit(c, b, g, h, minv, vel0, r, rhs, rhs_w, intact, w_diag_n)
        alpha, best = 0.0, phi0
        for e in range(7):
            trial_r = r + 0.5 ** e * (rnew - r)
            trial_v = vel0 + minv * (h.T @ (trial_r - r).ravel())
            phi = merit(c, b, g, h, minv, trial_v, trial_r, rhs, rhs_w, intact, w_diag_n)
            if phi < phi0:
                alpha, best = 0.5 ** e, phi
                break
        stats.update(alpha=alpha, merit0=phi0, merit=best)
        dr = alpha * (rnew - r)
    else:
        dr = DAMPING * (rnew - r)        # a damped step
    rnew = r + dr
    dvel = (minv * (h.T @ dr.ravel())).reshape(n, 6)
    c = dict(c, r=rnew[:mc])
    b = dict(b, r=rnew[mc:])
    g = dict(g, v=g["v"] + dvel[:, :3], w=g["w"] + dvel[:, 3:])
    write(sim, c, b, g)
    stats.update(open=int(open_.sum()), stick=int(stick.sum()), slide=int(slide.sum()),
                 bonds=int(intact.sum()), unknowns=K.shape[0], nnz=K.nnz,
                 fill=lu.L.nnz + lu.U.nnz, assemble_s=t1 - t0, solve_s=t2 - t1,
                 change=float(np.abs(dr).sum() / max(np.abs(rnew).sum(), 1e-300)))


def merit(c, b, g, h, minv, vel, r, rhs, rhs_w, intact, w_diag_n):
    """The squared natural-map residual of every item at impulses r and velocities vel: a
    contact's R - proj_cone(R - (u + rhs n) / W_nn), an intact bond's (u + C R + rhs) /
    (W_nn + c_n), in impulse units."""
    mc = len(c["i"])
    u = (h @ vel).reshape(-1, 3) + (rhs_w - rhs)         # with the walls' side
    cn_ = c["nrm"]
    x = r[:mc] - (u[:mc] + rhs[:mc]) / w_diag_n[:, None]
    xn = np.maximum((x * cn_).sum(1), 0.0)
    xt = x - (x * cn_).sum(1)[:, None] * cn_
    tn = np.linalg.norm(xt, axis=1)
    sc = np.where(tn > c["mu"] * xn, c["mu"] * xn / np.maximum(tn, 1e-300), 1.0)
    fc = r[:mc] - (xn[:, None] * cn_ + sc[:, None] * xt)
    bn = b["nrm"]
    rb = r[mc:]
    rbn = (rb * bn).sum(1)
    eb = u[mc:] + b["cn"][:, None] * rbn[:, None] * bn + b["ct"][:, None] * (rb - rbn[:, None] * bn) + rhs[mc:]
    wb = g["im"][b["i"]] + g["im"][b["j"]] + b["cn"]
    fb = np.where(intact[:, None], eb / wb[:, None], 0.0)
    return float((fc ** 2).sum() + (fb ** 2).sum())


def snapshot(sim):
    c, b, g = read(sim)
    return np.concatenate([c["r"].ravel(), b["r"].ravel()]), np.concatenate([g["v"], g["w"]], 1)


def rel(a, b):
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("scenario")
    ap.add_argument("--time-step", type=float, default=2e-4)
    ap.add_argument("--settle-steps", type=int, default=20)
    ap.add_argument("--settle-tolerance", type=float, default=1e-5)
    ap.add_argument("--sweeps", type=int, default=5, help="Gauss-Seidel sweeps before each direct solve")
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--reference-sweeps", type=int, default=60000)
    ap.add_argument("--eps", type=float, default=1e-6, help="the contacts' regularising compliance, relative to W_nn")
    ap.add_argument("--damping", type=float, default=1.0, help="the fraction of the solve's change taken")
    ap.add_argument("--line-search", action="store_true", help="take the largest of 1, 1/2, ... 1/64 of the solve's change that lowers the natural-map merit (else none)")
    ap.add_argument("--hold-contacts", action="store_true", help="solve the bonds alone exactly, the contacts' impulses held (block Gauss-Seidel)")
    a = ap.parse_args(argv)
    global EPS, HOLD_CONTACTS, DAMPING, LINE_SEARCH
    EPS, HOLD_CONTACTS, DAMPING, LINE_SEARCH = a.eps, a.hold_contacts, a.damping, a.line_search
    import tcd
    tcd.init("cpu", "f64")
    from tcd import config, io, runner, solver as sk
    scn = config.parse_scenario(Path(a.scenario).read_text(), a.scenario, resolve_samples=False)
    arrays, meta = io.load_checkpoint(a.checkpoint)
    sim = runner.restore_simulation(scn, arrays, meta)
    sim.settings = dataclasses.replace(sim.settings, time_step=a.time_step,
                                       tolerance=a.settle_tolerance)
    for _ in range(a.settle_steps):
        sim.step()
    d, t, kstep = sim.state_dict(), sim.time, sim.step_index
    flags = sim._sweep_flags()
    p, wl, bd = sim.particles, sim.wall_fields, sim.bonds

    def begin():
        sim.load_state_dict(d)
        sim.time, sim.step_index = t, kstep
        sim._begin_step(warm_start=True)

    def sweeps(k, tol=1e-300):
        """k sweeps (fewer if the residual falls below tol): the last sweep's residual."""
        sk.nlgs_serial(p, wl, sim.contacts, bd, sim.stats, k, tol, 1, *flags)
        return float(sim.stats.residual[None])

    t0 = time.perf_counter()
    begin()
    sweeps(a.reference_sweeps, 1e-13)
    ref_r, ref_v = snapshot(sim)
    print(f"reference: {a.reference_sweeps} sweeps at most, residual {float(sim.stats.residual[None]):.2e}, "
          f"{time.perf_counter() - t0:.0f} s; {int(sim.contacts.total[None])} contacts, "
          f"{int(bd.total[None])} bonds", flush=True)
    k = max(a.sweeps, 1)
    begin()
    print(f"\n{k} sweeps per round ({'symmetric' if flags[0] else 'forward'}, "
          f"{'NNCG' if flags[1] else 'plain'}):")
    print("| round | sweeps so far | residual (tcd) | impulses off | velocities off | open / stick / "
          "slide / bonds | unknowns | nnz K / LU | assemble, factor+solve (s) | change of the solve |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for rnd in range(a.rounds):
        res = sweeps(k)
        r, v = snapshot(sim)
        st = {}
        direct_round(sim, *read(sim), st)
        print(f"| {rnd} | {(rnd + 1) * k} | {res:.2e} | {rel(r, ref_r):.2e} | {rel(v, ref_v):.2e} | "
              f"{st['open']} / {st['stick']} / {st['slide']} / {st['bonds']} | {st['unknowns']} | "
              f"{st['nnz']} / {st['fill']} | {st['assemble_s']:.2f}, {st['solve_s']:.2f} | "
              f"{st['change']:.2e} |" + (f" step {st['alpha']:g}, merit {st['merit0']:.3e} -> "
                                         f"{st['merit']:.3e}" if "alpha" in st else ""), flush=True)
    res = sweeps(1)
    r, v = snapshot(sim)
    print(f"| end | {a.rounds * k + 1} | {res:.2e} | {rel(r, ref_r):.2e} | {rel(v, ref_v):.2e} "
          "| | | | | |", flush=True)
    line = []                            # the sweeps alone, for comparison
    for kk in (17, 100, 1000):
        begin()
        res = sweeps(kk)
        r, v = snapshot(sim)
        line.append(f"{kk}: residual {res:.2e}, impulses {rel(r, ref_r):.2e}, "
                    f"velocities {rel(v, ref_v):.2e}")
    print("sweeps alone: " + "; ".join(line), flush=True)

if __name__ == "__main__":
    main()
