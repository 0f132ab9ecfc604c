"""Coarse (two-level) corrections between Gauss-Seidel sweeps on the pour's impact step: a
prototype in NumPy, not part of tcd (session 25), kept runnable.

The state is the one of `solver_convergence.py` (2600 binder spheres of `tcd bench pour` at
t = 0.48 s, about 6500 contacts; poured once, about 2-4 min, and cached in a pickle). The step
is prepared as `Simulation._step` does (walls, contacts, predictor, contact geometry, warm
start); then `solver.nlgs_serial` runs blocks of K plain symmetric sweeps (tolerance never
reached) and, between blocks, the correction below is computed in NumPy and written back
(impulses, and the body velocities by the same M^-1 H^T dR, so v = v_free + M^-1 H^T R holds).

The correction is Galerkin on the current active set: contacts with R_n > 0; their normal
velocity error u_n + g/(theta H), plus the tangential velocity of the sticking ones, is g; with
a coarse basis Q (columns: impulse patterns over the contacts) the coarse impulses c solve
(Q^T W Q) c = -Q^T g (W = H M^-1 H^T, assembled from the bodies' responses to each column),
R += Q c, then R is projected on the friction cones. Bases (`--basis`), over a grid of
`--spacing` metres:
  - scale: per grid node, the current impulses of the contacts around it, weighted by the
    trilinear hat of the node (one unknown per node: the local level of the force network);
  - stress: per node, a symmetric stress tensor sigma (6 unknowns), contact impulse
    (r_i + r_j)^2 N(x_c) sigma n (the inverse of the Love-Weber average);
  - roll: scale, plus per node three tangential patterns R_n (e_a x n), a = x, y, z (the
    contacts' share of a rotation of the node's neighbourhood);
  - iface: bodies grouped by grid cell (each wall its own group); one 3-vector per pair of
    groups in contact, spread equally over the contacts between them.
`--frictionless` sets every contact's friction to zero before the step (a check that the
machinery works where the problem is a plain linear complementarity one).

    python benchmarks/coarse_correction.py [--basis scale] [--spacing 0.02,0.01] [--frictionless]
        [--block 20] [--sweeps 300]

Session 25 (this 2-core CPU, f64; residual = tcd's measure, sum |dR| / sum |R| of the block's
last sweep, after 300 sweeps; plain symmetric Gauss-Seidel, blocks of 20):
  - frictionless: no correction 7.37e-4; scale 0.02 m 4.39e-5, 0.01 m 8.36e-6 (1e-4 reached
    after about 220 and 140 sweeps); stress 0.03 m 6.38e-4, 0.02 m 4.80e-4.
  - friction 0.7 (the benchmark's): no correction 4.52e-4; scale 0.02 m 4.31e-4, 0.01 m
    4.15e-4; scale with separate normal and tangential levels 0.01 m 3.92e-4; stress 0.03 m
    4.49e-4 (600 sweeps: 2.49e-4 against 2.52e-4); iface 0.02 m 4.56e-4; roll 0.02 m 4.33e-4. Testing with the
    normal direction only on the sliding contacts (Petrov-Galerkin) changed nothing.
  - friction 0.7 with the rotations locked (a diagnostic: inverse inertia zeroed; script not
    shipped): no correction 5.55e-4, scale 0.02 m 1.75e-4, 0.01 m 1.48e-4.
  So a coarse level removes the frictionless bed's slow load redistribution, but with friction
  the slow part is elsewhere: 33 % of the active contacts slide, the active and sliding sets
  hardly change (about 20 contacts change state in 20 sweeps), and 72 % of what still changes
  after 300 sweeps is on sticking contacts (58 % normal, 34 % tangential components).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout
sys.path.insert(0, str(Path(__file__).resolve().parent))
import tcd  # noqa: E402
import solver_convergence  # noqa: E402
from tcd import bench, solver as sk  # noqa: E402
from tcd.state import get  # noqa: E402

def _symmetric_basis():
    out = []
    for a in range(3):
        for b in range(a, 3):
            e = np.zeros((3, 3))
            e[a, b] = e[b, a] = 1.0
            out.append(e)
    return np.array(out)


SYM = _symmetric_basis()


class Step:
    def __init__(self, state, t, frictionless):
        self.state, self.t, self.frictionless = state, t, frictionless
        self.sim = bench.pour_setup(2600, 1, 1e-4)

    def prepare(self):
        ct = solver_convergence.begin_step(self.sim, self.state, self.t)
        if self.frictionless:
            ct.mu.fill(0.0)
            r, nrm = ct.impulse.to_numpy(), ct.normal.to_numpy()
            ct.impulse.from_numpy((r * nrm).sum(1)[:, None] * nrm)
        sk.apply_warm_start(self.sim.particles, ct, self.sim.bonds)

    def sweeps(self, k, accel=0):
        """k symmetric sweeps; accel 1: with NNCG momentum (restarted at each call)."""
        sim = self.sim
        sk.nlgs_serial(sim.particles, sim.wall_fields, sim.contacts, sim.bonds, sim.stats, k,
                       1e-300, 1, 1, accel, 0, 0)
        return float(sim.stats.residual[None])

    def arrays(self):
        return contact_arrays(self.sim)

    def write_back(self, d, rnew):
        ct, p = self.sim.contacts, self.sim.particles
        dv, dw = body_response(d, rnew - d["r"])
        for field, rows in ((ct.impulse, rnew), (p.v, d["v"] + dv), (p.w, d["w"] + dw)):
            write_rows(field, rows)


# --- shared by the NumPy solver prototypes (coarse_correction, krylov_*, jacobi_shear,
# pour_reference): the contacts and bodies as arrays, and H, H^T and the Delassus diagonal
def contact_arrays(sim):
    """The contacts and the bodies of `sim` as NumPy arrays (the prototypes' `d`)."""
    ct, p = sim.contacts, sim.particles
    m, n = int(ct.total[None]), sim.n
    return dict(i=get(ct.i, m), j=get(ct.j, m), nrm=get(ct.normal, m), r=get(ct.impulse, m),
                rhs=get(ct.rhs, m), mu=get(ct.mu, m), x=get(p.x, n), v=get(p.v, n),
                w=get(p.w, n), rad=get(p.radius, n), im=get(p.inv_mass, n),
                ii=get(p.inv_inertia, n), wallv=sim.wall_fields.velocity.to_numpy())


def write_rows(field, rows):
    """Write `rows` over the first rows of a Taichi field, keeping the rest."""
    full = field.to_numpy()
    full[: len(rows)] = rows
    field.from_numpy(full)


def body_response(d, dr, im=None, spin=None):
    """The bodies' velocity and spin changes M^-1 H^T dR for item impulse changes dr (a wall
    side, j >= particles, takes nothing). `im`, `spin`: per body weights instead of the
    inverse mass and inverse inertia times radius (ones: the resultant impulse and moment /
    radius)."""
    i, j, nrm, n = d["i"], d["j"], d["nrm"], len(d["x"])
    im = d["im"] if im is None else im
    spin = d["ii"] * d["rad"] if spin is None else spin
    dv, dw = np.zeros((n, 3)), np.zeros((n, 3))
    c = np.cross(nrm, dr)
    part = j < n
    jp = j[part]
    np.add.at(dv, i, -dr * im[i][:, None])
    np.add.at(dw, i, -spin[i][:, None] * c)
    np.add.at(dv, jp, dr[part] * im[jp][:, None])
    np.add.at(dw, jp, -spin[jp][:, None] * c[part])
    return dv, dw


def velocity_jump(d, v, w, wallv=None):
    """H (v, w): each item's relative velocity of its j side over its i side at the contact
    point, for body velocities v and spins w; a wall side moves at wallv (none: at rest)."""
    i, j, nrm, n = d["i"], d["j"], d["nrm"], len(d["x"])
    part = j < n
    jj = np.where(part, j, 0)
    vj = np.where(part[:, None], v[jj], 0.0 if wallv is None else wallv[np.where(part, 0, j - n)])
    spin = d["rad"][i][:, None] * w[i] + np.where(part[:, None], d["rad"][jj][:, None] * w[jj], 0.0)
    return vj - v[i] - np.cross(spin, nrm)


def relative_velocity(d):
    return velocity_jump(d, d["v"], d["w"], d["wallv"])


def delassus_diagonal(d, im=None, ii=None):
    """The items' Delassus diagonal in their frames, (normal, tangential), for the bodies'
    inverse masses and inertias (or `im`, `ii` in their place)."""
    i, j, n = d["i"], d["j"], len(d["x"])
    im = d["im"] if im is None else im
    ii = d["ii"] if ii is None else ii
    part = j < n
    jj = np.where(part, j, 0)
    wnn = im[i] + np.where(part, im[jj], 0.0)
    wtt = wnn + ii[i] * d["rad"][i] ** 2 + np.where(part, ii[jj] * d["rad"][jj] ** 2, 0.0)
    return wnn, wtt


def basis(d, spacing, kind, active, slide):
    """Q: (contacts, columns, 3) impulse patterns."""
    i, j, nrm, r, n = d["i"], d["j"], d["nrm"], d["r"], len(d["x"])
    m, part = len(i), d["j"] < len(d["x"])
    rad = d["rad"]
    if kind == "iface":
        cell = np.floor((d["x"] - d["x"].min(0)) / spacing).astype(np.int64)
        nc = cell.max(0) + 1
        group = (cell[:, 0] * nc[1] + cell[:, 1]) * nc[2] + cell[:, 2]
        a = group[i]
        b = np.where(part, group[np.where(part, j, 0)], int(nc.prod()) + (j - n))
        across = np.nonzero(active & (a != b))[0]
        keys, pair = np.unique(np.stack([a[across], b[across]], 1), axis=0, return_inverse=True)
        q = np.zeros((m, 3 * len(keys), 3))
        for c, t in zip(across, pair.ravel()):
            q[c, 3 * t: 3 * t + 3] = np.outer(nrm[c], nrm[c]) if slide[c] else np.eye(3)
        return q
    xc = d["x"][i] + rad[i][:, None] * nrm
    lo, hi = xc[active].min(0) - 1e-9, xc[active].max(0) + 1e-9
    nn = np.maximum(np.ceil((hi - lo) / spacing).astype(int), 1) + 1
    f = np.clip((xc - lo) / ((hi - lo) / (nn - 1)), 0, nn - 1 - 1e-9)
    c0 = np.floor(f).astype(int)
    t = f - c0
    per = {"scale": 1, "roll": 4, "stress": 6}[kind]
    q = np.zeros((m, int(nn.prod()) * per, 3))
    rows = np.arange(m)
    if kind == "stress":
        other = np.where(part, rad[np.where(part, j, 0)], rad[i])
        pattern = ((rad[i] + other) ** 2)[:, None, None] * np.einsum("sab,cb->csa", SYM, nrm)
    elif kind == "roll":         # the node's share, and R_n (e_a x n) for a = x, y, z
        rn = (r * nrm).sum(1)
        pattern = np.concatenate([r[:, None, :], rn[:, None, None] * np.cross(np.eye(3)[None, :, :], nrm[:, None, :])], 1)
    else:
        pattern = r[:, None, :]
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                hat = ((t[:, 0] if dx else 1 - t[:, 0]) * (t[:, 1] if dy else 1 - t[:, 1])
                       * (t[:, 2] if dz else 1 - t[:, 2]))
                node = ((c0[:, 0] + dx) * nn[1] + (c0[:, 1] + dy)) * nn[2] + (c0[:, 2] + dz)
                for s in range(per):
                    np.add.at(q, (rows, node * per + s), hat[:, None] * pattern[:, s, :])
    q[~active] = 0.0
    return q[:, np.abs(q).sum((0, 2)) > 0, :]


def correction(d, spacing, kind):
    i, j, nrm, r, n = d["i"], d["j"], d["nrm"], d["r"], len(d["x"])
    part = j < n
    u = relative_velocity(d)
    un, rn = (u * nrm).sum(1), (r * nrm).sum(1)
    rt = r - rn[:, None] * nrm
    active = rn > 0
    slide = active & (np.linalg.norm(rt, axis=1) >= d["mu"] * rn * (1 - 1e-9))
    g = np.where(active[:, None], (un + d["rhs"])[:, None] * nrm, 0.0)
    stick = active & ~slide
    g[stick] += (u - un[:, None] * nrm)[stick]
    q = basis(d, spacing, kind, active, slide)
    cols = q.shape[1]
    body = np.zeros((n, 6, cols))          # each column's impulse and torque on every body
    nxq = np.transpose(np.cross(nrm[:, None, :], q), (0, 2, 1))
    qt = np.transpose(q, (0, 2, 1))
    np.add.at(body, (i, slice(0, 3)), -qt)
    np.add.at(body, (i, slice(3, 6)), -d["rad"][i][:, None, None] * nxq)
    jp = j[part]
    np.add.at(body, (jp, slice(0, 3)), qt[part])
    np.add.at(body, (jp, slice(3, 6)), -d["rad"][jp][:, None, None] * nxq[part])
    minv = np.concatenate([np.repeat(d["im"][:, None], 3, 1), np.repeat(d["ii"][:, None], 3, 1)], 1)
    gb = body.reshape(n * 6, cols)
    wc = gb.T @ (minv.reshape(-1)[:, None] * gb)
    c = -np.linalg.solve(wc + 1e-12 * np.trace(wc) / cols * np.eye(cols), np.einsum("cma,ca->m", q, g))
    rnew = r + np.einsum("cma,m->ca", q, c)
    rnn = (rnew * nrm).sum(1)
    tang = rnew - rnn[:, None] * nrm
    rnn = np.maximum(rnn, 0.0)
    nt, limit = np.linalg.norm(tang, axis=1), d["mu"] * rnn
    scale = np.where(nt > limit, limit / np.maximum(nt, 1e-300), 1.0)
    return rnn[:, None] * nrm + scale[:, None] * tang


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--state", default="/tmp/tcd_pour_state.pkl")
    ap.add_argument("--time", type=float, default=0.48)
    ap.add_argument("--basis", default="scale", choices=("scale", "stress", "iface", "roll"))
    ap.add_argument("--spacing", default="0.02,0.01")
    ap.add_argument("--frictionless", action="store_true")
    ap.add_argument("--block", type=int, default=20)
    ap.add_argument("--sweeps", type=int, default=300)
    a = ap.parse_args()
    tcd.init("cpu", "f64")
    step = Step(solver_convergence.pour_state(2600, a.time, a.state), a.time, a.frictionless)
    for spacing in [None] + [float(s) for s in a.spacing.split(",")]:
        t0 = time.perf_counter()
        step.prepare()
        done, line = 0, []
        while done < a.sweeps:
            k = min(a.block, a.sweeps - done)
            residual = step.sweeps(k)
            done += k
            line.append(f"{done}:{residual:.2e}")
            if spacing and done < a.sweeps:
                d = step.arrays()
                step.write_back(d, correction(d, spacing, a.basis))
        label = f"{a.basis} {spacing} m" if spacing else "no correction"
        print(f"{label} ({time.perf_counter() - t0:.0f} s): " + " ".join(line[4::5]), flush=True)


if __name__ == "__main__":
    main()
