"""Nonlinear Gauss-Seidel over frictional contacts and bonds (PHYSICS.md sections 2-6).

Each local problem is solved exactly (laws.py) with the latest body velocities, and its impulse
increment is applied to the two bodies at once, so the contacts see each other implicitly
through the body velocities. Four schedules run the same local solves:
- "serial": every sweep visits bonds then contacts in canonical order inside ONE kernel launch
  for all sweeps (no launch overhead; the true sequential NLGS). Best on a few CPU cores.
- "coloured": bond items (particle bond blocks, or single bonds) and contacts are greedily
  coloured so that one colour never shares a dynamic body (walls excepted); the items of one
  colour are solved in parallel, colour after colour, one launch per colour. For many-core
  devices (GPU).
- "resident": the coloured schedule's colours and local solves, but all sweeps of a step in
  ONE launch: one GPU thread block per system stays resident for the whole step and meets
  at a block barrier after each colour (solve_resident). No launch per colour; on the CPU a
  block is one thread, and the numbers are the coloured schedule's.
- "partitioned" (tcd/partitioned.py): the serial sweep split over P CPU threads (P slabs of
  particles across the sample, their interior items at once, then the boundary items), all sweeps in
  one launch. Numbers depend on P, never on thread timing.
Convergence: the relative change of impulses over a sweep, sum |dR| / sum |R| (measure
"impulse", PHYSICS.md section 6), checked every `check_every` sweeps (and at `max_sweeps`);
the step stops when it is below `tolerance` or at `max_sweeps`. The two norms per contact are
only computed on the sweeps that check. Measure "quad" is LMGC90's 'Quad ' check instead
(check_item_bond, check_item_contact, quad_residual): a pass that updates nothing and
measures, in velocity, the correction every local solve would still make.
Existing overlap (g_beg < 0) is not corrected: the target end gap is max(g_beg, 0), so a
converged step injects no energy and never adds overlap (contacts.contact_geometry).
Everything here is deterministic: no float atomics, reductions in a fixed order. Body and
contact updates are plain load/store (no atomics): no two threads ever touch one body.
"""

import os

import taichi as ti

from . import backend, contacts, laws
from .state import (COLOUR_WORDS, MAX_COLOURS, MOMENTUM_CHUNK, MOMENTUM_GROUPS, RESIDUAL_CHUNK,
                    WALL_CHUNK)

INTACT, BROKEN_TENSION, BROKEN_SHEAR = 0, 1, 2
SYSTEM_SPREAD = 1024         # loop iterations per batched system (see nlgs_serial)
MODE_PAPER, MODE_BURGERS = 0, 1
# A visit to a contact that carries no impulse and whose local solve keeps it open (its normal
# relative velocity with the gap term is not approaching: R.n would be max(0, -x) = 0, hence
# R = 0) changes nothing: the visit returns after that test, without the friction cone or the
# four zero updates of its bodies (bit for bit the same numbers, up to the sign of a zero
# impulse; measured: a quarter of the pour's sweep cost, session 35). The environment
# variable TCD_OPEN_SKIP=0 turns the early return off (read at import), for comparisons.
OPEN_SKIP = backend.env_flag("TCD_OPEN_SKIP", True)


@ti.func
def impulse_residual(dsum, rsum):
    """The impulse convergence measure sum |dR| / sum |R| of a sweep. A sweep that unloaded
    every impulse (sum |R| = 0) but changed some has not converged: it may have left an
    earlier-visited contact approaching, so it measures 1, not 0."""
    residual = 0.0
    if rsum > 0.0:
        residual = dsum / rsum
    elif dsum > 0.0:
        residual = 1.0
    return residual


# --- body access (j >= n is a wall: kinematic, infinite mass) --------------------------------
@ti.func
def point_velocity(p: ti.template(), wl: ti.template(), b, offset):
    u = ti.Vector([0.0, 0.0, 0.0])
    if b < p.count[None]:
        u = p.v[b] + p.w[b].cross(offset)
    else:
        u = wl.velocity[b - p.count[None]]
    return u


@ti.func
def apply_impulse(p: ti.template(), i, j, n, dr):
    """A contact's impulse: dr on j at -r_j n, -dr on i at r_i n."""
    rj = 0.0
    if j < p.count[None]:
        rj = p.radius[j]
    apply_impulse_at(p, i, j, n, dr, p.radius[i], rj)


@ti.func
def apply_impulse_at(p: ti.template(), i, j, n, dr, ai, aj):
    """Impulse dr on j at -aj n from its centre, -dr on i at ai n from its centre."""
    # plain load/store (no atomics): callers never let two threads touch one body
    p.v[i] = p.v[i] - dr * p.inv_mass[i]
    p.w[i] = p.w[i] - p.inv_inertia[i] * (ai * n).cross(dr)
    if j < p.count[None]:
        p.v[j] = p.v[j] + dr * p.inv_mass[j]
        p.w[j] = p.w[j] + p.inv_inertia[j] * (-aj * n).cross(dr)


@ti.func
def bond_arms(p: ti.template(), bd: ti.template(), b):
    """Lever arms (a_i, a_j) of bond b: it acts at the middle of the gap, a_i = r_i + g/2 from
    i's centre along n and a_j = r_j + g/2 from j's against it (g the gap at the step's start,
    bonds_prepare). Both grains' velocities are taken at that one point, so a rigid motion of
    the pair gives no relative velocity whatever the gap (at the surfaces, r_i n and -r_j n,
    two points g apart, a rigid spin w would give w x (g n))."""
    hg = bd.half_gap[b]
    return p.radius[bd.i[b]] + hg, p.radius[bd.j[b]] + hg


@ti.func
def apply_bond_impulse(p: ti.template(), bd: ti.template(), b, dr):
    """Impulse dr on bond b's j, -dr on its i, at the middle of its gap (bond_arms)."""
    ai, aj = bond_arms(p, bd, b)
    apply_impulse_at(p, bd.i[b], bd.j[b], bd.normal[b], dr, ai, aj)


@ti.func
def relative_velocity(p: ti.template(), wl: ti.template(), i, j, n):
    """A contact's relative velocity: j's at -r_j n less i's at r_i n."""
    rj = 0.0
    if j < p.count[None]:
        rj = p.radius[j]
    return relative_velocity_at(p, wl, i, j, n, p.radius[i], rj)


@ti.func
def relative_velocity_at(p: ti.template(), wl: ti.template(), i, j, n, ai, aj):
    return point_velocity(p, wl, j, -aj * n) - (p.v[i] + p.w[i].cross(ai * n))


@ti.func
def bond_relative_velocity(p: ti.template(), wl: ti.template(), bd: ti.template(), b):
    """Bond b's relative velocity at the middle of its gap (bond_arms)."""
    ai, aj = bond_arms(p, bd, b)
    return relative_velocity_at(p, wl, bd.i[b], bd.j[b], bd.normal[b], ai, aj)


@ti.func
def solve_contact(p: ti.template(), wl: ti.template(), ct: ti.template(), k, n_part, measure):
    """Local solve of contact k against the current body velocities; n_part: particle count
    (j >= n_part is a wall). Returns (|dR|, |R|) when `measure` is 1, else zeros (the two
    square roots are only paid on the sweeps that check convergence)."""
    dr, r_new = solve_contact_dr(p, wl, ct, k, n_part)
    da = 0.0
    ra = 0.0
    if measure == 1:
        da, ra = dr.norm(), r_new.norm()
    return da, ra


@ti.func
def contact_law(u, r_old, n, wnn, wtt, rhs, mu):
    """A frictional contact's local solve: its new impulse, given the relative velocity u
    with its current impulse r_old applied, its Delassus diagonal (wnn, wtt, wtt in its frame)
    and its gap term and friction (laws.signorini_coulomb on the free velocity)."""
    un = u.dot(n)
    rn_old = r_old.dot(n)
    ufn = un - wnn * rn_old
    uft = (u - un * n) - wtt * (r_old - rn_old * n)
    rn, rt = laws.signorini_coulomb(ufn, uft, rhs, 1.0 / wnn, 1.0 / wtt, mu)
    return rn * n + rt


@ti.func
def solve_contact_dr(p: ti.template(), wl: ti.template(), ct: ti.template(), k, n_part):
    """Local solve of contact k; returns (dR, R) (zero vectors if both bodies are kinematic,
    or if the contact has no impulse and stays open: OPEN_SKIP).

    For spheres the relative velocity at the contact is u = v_j - v_i - (r_i w_i + r_j w_j) x n
    and an impulse dR on j (-dR on i) changes w_i and w_j by -(I^-1 r) (n x dR): one cross
    product each way."""
    dr = ti.Vector([0.0, 0.0, 0.0])
    r_new = ti.Vector([0.0, 0.0, 0.0])
    wnn = ct.wnn[k]
    if wnn > 0.0:             # two kinematic bodies: nothing to solve
        i, j, n = ct.i[k], ct.j[k], ct.normal[k]
        r_old = ct.impulse[k]
        ri = p.radius[i]
        spin = ri * p.w[i]
        vj = ti.Vector([0.0, 0.0, 0.0])
        rj = 0.0
        if j < n_part:
            rj = p.radius[j]
            vj = p.v[j]
            spin += rj * p.w[j]
        else:
            vj = wl.velocity[j - n_part]
        u = vj - p.v[i] - spin.cross(n)
        rhs = ct.rhs[k]
        stays_open = 0
        if ti.static(OPEN_SKIP):
            # no impulse and not approaching: the law gives R = 0 (see OPEN_SKIP)
            if r_old[0] == 0.0 and r_old[1] == 0.0 and r_old[2] == 0.0:
                if u.dot(n) + rhs >= 0.0:
                    stays_open = 1
        if stays_open == 0:
            r_new = contact_law(u, r_old, n, wnn, ct.wtt[k], rhs, ct.mu[k])
            dr = r_new - r_old
            c = n.cross(dr)
            # plain load/store (no atomics): callers never let two threads touch one body
            p.v[i] = p.v[i] - dr * p.inv_mass[i]
            p.w[i] = p.w[i] - (p.inv_inertia[i] * ri) * c
            if j < n_part:
                p.v[j] = p.v[j] + dr * p.inv_mass[j]
                p.w[j] = p.w[j] - (p.inv_inertia[j] * rj) * c
            ct.impulse[k] = r_new
    return dr, r_new


@ti.func
def solve_bond_turn(p: ti.template(), bd: ti.template(), b):
    """The turn of intact bond b's frame over the step, when on (bd.turn_on: the
    `bond_frame = "end"` setting). The bond's normal force R_n acts along its frame of the
    step's start, n; at the end of the step it acts along the new line of centres,
    n + theta H P (v_j - v_i) / L to first order (P = I - n n^T, L the distance of the centres).
    The difference, a central impulse G = R_n theta H P (v_j - v_i) / L, is solved here against
    the current velocities (a damper between the centres, implicit in them): frozen at the
    step's start, the frame makes a grain rolling about one loaded bond an explicit pendulum,
    unstable above F H^2 / (m L) = 5.6 (docs/physics.md, "Limitations"). Only in tension
    (R_n < 0): under compression the turn pushes the grain further (an inverted pendulum), which
    an implicit term would not capture better. Its coefficient kappa = -R_n theta H / L is set
    per step from the warm start's R_n (bonds_prepare; the sweeps' own R_n would couple the two
    unsymmetrically). The bond-by-bond relaxation solves it after its bond; the particle
    blocks solve it inside the block (solve_particle_bonds: a damper of stiffness
    kappa / (1 + kappa m_o^-1) P on q's translation). The conjugate-gradient momentum does
    not move it, and is refused with it (SolverSettings)."""
    kappa = turn_coefficient(bd, b)
    if kappa > 0.0 and bd.state[b] == INTACT:
        i, j, n = bd.i[b], bd.j[b], bd.normal[b]
        g_old = bd.turn[b]
        w = p.inv_mass[i] + p.inv_mass[j]
        # the relative velocity of the centres without this impulse, in the tangent plane
        other = (p.v[j] - p.v[i]) - w * g_old
        other = other - other.dot(n) * n
        g_new = -(kappa / (1.0 + kappa * w)) * other
        dg = g_new - g_old
        p.v[i] = p.v[i] - dg * p.inv_mass[i]
        p.v[j] = p.v[j] + dg * p.inv_mass[j]
        bd.turn[b] = g_new


@ti.func
def turn_coefficient(bd: ti.template(), b):
    """Bond b's turn coefficient kappa (solve_bond_turn); 0 when the turn is off, whose
    fields then hold one slot (Bonds: `turn`)."""
    kappa = 0.0
    if bd.turn_on[None] == 1:
        kappa = bd.turn_k[b]
    return kappa


@ti.func
def solve_bond(p: ti.template(), wl: ti.template(), bd: ti.template(), b):
    dr, r_new = solve_bond_dr(p, wl, bd, b)
    return dr.norm(), r_new.norm()


@ti.func
def solve_bond_dr(p: ti.template(), wl: ti.template(), bd: ti.template(), b):
    dr = ti.Vector([0.0, 0.0, 0.0])
    r_new = ti.Vector([0.0, 0.0, 0.0])
    if bd.state[b] == INTACT:
        r_old = bd.impulse[b]
        r_new, _, _ = bond_law(p, wl, bd, b, r_old)
        dr = r_new - r_old
        apply_bond_impulse(p, bd, b, dr)
        bd.impulse[b] = r_new
        solve_bond_turn(p, bd, b)
    return dr, r_new


@ti.func
def bond_law(p: ti.template(), wl: ti.template(), bd: ti.template(), b, r_old):
    """Intact bond b's local solve on its own at the current body velocities, from impulse
    r_old: (its new impulse, W_nn, W_tt of its Delassus diagonal)."""
    i, j, n = bd.i[b], bd.j[b], bd.normal[b]
    u = bond_relative_velocity(p, wl, bd, b)
    un = u.dot(n)
    ut = u - un * n
    rn_old = r_old.dot(n)
    rt_old = r_old - rn_old * n
    ai, aj = bond_arms(p, bd, b)
    wnn = p.inv_mass[i] + p.inv_mass[j]
    wtt = wnn + ai * ai * p.inv_inertia[i] + aj * aj * p.inv_inertia[j]
    ufn = un - wnn * rn_old
    uft = ut - wtt * rt_old
    rn, rt = laws.bonded(ufn, uft, bd.rhs_n[b], bd.rhs_t[b], wnn, wtt, bd.cn[b], bd.ct[b])
    return rn * n + rt, wnn, wtt


# --- LMGC90's 'Quad ' convergence check (measure "quad") -----------------------------------------
# LMGC90 (mod_nlgs, check type 'Quad ') checks convergence with a pass that updates nothing: for
# each interaction, R is its impulse and R' what its local solve would make of it at the
# current body velocities; dV = W (R - R') is the velocity correction still to come, W the
# interaction's diagonal block of the Delassus operator (diag(wnn, wtt, wtt) in its frame for
# spheres; a bond's compliance is not in W). With R_m = (R + R') / 2, WRR = (W R . R +
# W R' . R') / 2 and WRWR = (|W R|^2 + |W R'|^2) / 2, summed over the interactions (N: those
# with R_m != 0):
#   QuadDV = sqrt(sum |dV|^2 / sum WRWR), QuadDVR = sqrt(sum |dV|^2 |R_m|^2 / N) / (sum WRR / N),
#   MeanDVoR = sum R_m . dV / sum WRR,
# and the step has converged when all three are below the tolerance in absolute value: the
# residual reported is the largest of the three.
QUAD_SUMS = 6      # sum |dV|^2, sum |dV|^2 |R_m|^2, sum R_m . dV, sum WRR, sum WRWR, N


@ti.func
def quad_terms(r_old, r_new, n, wnn, wtt):
    """One interaction's terms of the 'Quad ' sums (see QUAD_SUMS)."""
    d = r_old - r_new
    dn = d.dot(n)
    dv = wnn * dn * n + wtt * (d - dn * n)
    ro = r_old.dot(n)
    rn = r_new.dot(n)
    wro = wnn * ro * n + wtt * (r_old - ro * n)
    wrn = wnn * rn * n + wtt * (r_new - rn * n)
    rm = 0.5 * (r_old + r_new)
    rm2 = rm.dot(rm)
    dv2 = dv.dot(dv)
    active = 0.0
    if rm2 > 0.0:
        active = 1.0
    return ti.Vector([dv2, dv2 * rm2, rm.dot(dv), 0.5 * (wro.dot(r_old) + wrn.dot(r_new)),
                      0.5 * (wro.dot(wro) + wrn.dot(wrn)), active])


@ti.func
def check_item_contact(p: ti.template(), wl: ti.template(), ct: ti.template(), k, n_part):
    """'Quad ' terms of contact k: its local solve (as solve_contact_dr) without applying it."""
    terms = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    wnn = ct.wnn[k]
    if wnn > 0.0:
        i, j, n = ct.i[k], ct.j[k], ct.normal[k]
        r_old = ct.impulse[k]
        u = relative_velocity(p, wl, i, j, n)
        wtt = ct.wtt[k]
        terms = quad_terms(r_old, contact_law(u, r_old, n, wnn, wtt, ct.rhs[k], ct.mu[k]), n,
                           wnn, wtt)
    return terms


@ti.func
def check_item_bond(p: ti.template(), wl: ti.template(), bd: ti.template(), b):
    """'Quad ' terms of bond b (intact): its own local solve (as solve_bond_dr) without
    applying it. A particle block's exact solution solves each of its bonds' equations, so
    a converged block relaxation leaves these terms at zero too."""
    terms = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    if bd.state[b] == INTACT:
        r_old = bd.impulse[b]
        r_new, wnn, wtt = bond_law(p, wl, bd, b, r_old)
        terms = quad_terms(r_old, r_new, bd.normal[b], wnn, wtt)
    return terms


@ti.func
def quad_values(sums):
    """(QuadDV, QuadDVR, MeanDVoR) from the QUAD_SUMS sums; zeros when nothing is loaded
    (LMGC90 then counts the step as converged too)."""
    out = ti.Vector([0.0, 0.0, 0.0])
    if sums[5] > 0.0 and sums[3] > 0.0 and sums[4] > 0.0:
        out = ti.Vector([ti.sqrt(sums[0] / sums[4]),
                         ti.sqrt(sums[1] / sums[5]) / (sums[3] / sums[5]),
                         sums[2] / sums[3]])
    return out


@ti.func
def quad_residual(sums):
    """max(QuadDV, QuadDVR, |MeanDVoR|) from the QUAD_SUMS sums (0 when nothing is loaded)."""
    v = quad_values(sums)
    return ti.max(v[0], ti.max(v[1], ti.abs(v[2])))


@ti.func
def quad_sums_range(p: ti.template(), wl: ti.template(), ct: ti.template(),
                    bd: ti.template(), b0, b1, c0, c1):
    """The 'Quad ' sums of bonds b0..b1 and contacts c0..c1 (serial, in item order)."""
    sums = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    n_part = p.count[None]
    for b in range(b0, b1):
        sums += check_item_bond(p, wl, bd, b)
    for k in range(c0, c1):
        sums += check_item_contact(p, wl, ct, k, n_part)
    return sums


@ti.func
def quad_check_range(p: ti.template(), wl: ti.template(), ct: ti.template(),
                     bd: ti.template(), b0, b1, c0, c1):
    """The 'Quad ' residual of bonds b0..b1 and contacts c0..c1 (serial, in item order)."""
    return quad_residual(quad_sums_range(p, wl, ct, bd, b0, b1, c0, c1))


@ti.kernel
def quad_norms(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
               out: ti.template()):
    """QuadDV, QuadDVR, MeanDVoR of all bonds and contacts at the current state into out[0..2]
    (Simulation.quad_norms)."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        v = quad_values(quad_sums_range(p, wl, ct, bd, 0, bd.total[None], 0, ct.total[None]))
        for m in ti.static(range(3)):
            out[m] = v[m]


# --- particle-block relaxation of the bonds ---------------------------------------------------
# Bonds are stiff on the time-step scale: h^2 K / m is 14 for a 16 mm grain and 7000 for a 2 mm
# one (K = 2e6 N/m, H = 2e-4 s). Solved one by one, the bonds of one light grain are nearly
# dependent (they all move the same 6 degrees of freedom, which their compliance barely
# regularises), and Gauss-Seidel crawls along that direction while the change per sweep looks
# converged: the bond forces then lag the geometry and the light grains store and release
# elastic energy that no converged step would. The block of particle q (all its intact bonds)
# is linear and each neighbour sits in one of its bonds only, so it is solved exactly: with e_b
# the residual u_b + C_b R_b + rhs_b of bond b seen from q (sign s = +1 when q is the bond's j,
# -1 when its i), G_b = [I, -S_b] (S_b the cross-product matrix of the unit offset -s n_b),
# K_b = (C_b + W_o)^-1 (W_o: the neighbour's contact-point mobility) and
# M' = diag(m, m, m, I/r^2, I/r^2, I/r^2) (rotation unknowns scaled by r):
#     (M' + sum G_b^T K_b G_b) xi = -sum G_b^T K_b e_b,   Q_b = -K_b (e_b + G_b xi),
# q receives the impulses Q_b (bond b's impulse changes by s Q_b), each neighbour its -Q_b.
# The residuals read before any update stay valid while the block is applied (q moves last,
# each neighbour belongs to one bond).
# Per step (bonds_factor, after bonds_prepare) the parts that do not change over the sweeps
# are computed once: K_b = beta I + (alpha - beta) n n^T (alpha = 1 / (cn + m_o^-1), beta =
# 1 / (ct + m_o^-1 + r_o^2 I_o^-1)) as (alpha, beta) per bond end, and the inverse of each
# particle's block matrix (21 entries of a symmetric 6 x 6). A sweep then pays per bond end
# one relative velocity and a few vector operations, and per particle one 6 x 6 product.
@ti.func
def cholesky_inverse6(a):
    """Inverse of a symmetric positive definite 6 x 6 matrix through its Cholesky factor
    (unrolled; columns of the identity substituted forward and back)."""
    lo = ti.Matrix.zero(float, 6, 6)
    for r in ti.static(range(6)):
        for c in ti.static(range(r + 1)):
            acc = a[r, c]
            for k in ti.static(range(c)):
                acc -= lo[r, k] * lo[c, k]
            if ti.static(r == c):
                lo[r, r] = ti.sqrt(ti.max(acc, 1e-30))
            else:
                lo[r, c] = acc / lo[c, c]
    inv = ti.Matrix.zero(float, 6, 6)
    for col in ti.static(range(6)):
        y = ti.Vector.zero(float, 6)
        for r in ti.static(range(6)):
            acc = 1.0 if ti.static(r == col) else 0.0
            for k in ti.static(range(r)):
                acc -= lo[r, k] * y[k]
            y[r] = acc / lo[r, r]
        for rr in ti.static(range(6)):
            r = ti.static(5 - rr)
            acc = y[r]
            for k in ti.static(range(r + 1, 6)):
                acc -= lo[k, r] * inv[k, col]
            inv[r, col] = acc / lo[r, r]
    return inv


# the 21 entries of a symmetric 6 x 6 matrix (lower triangle, row by row), as kept in
# Bonds.inverse
TRI6 = [(r, c) for r in range(6) for c in range(r + 1)]


@ti.func
def stiffness_apply(alpha, beta, n, x):
    """K x for K = beta I + (alpha - beta) n n^T."""
    return beta * x + ((alpha - beta) * n.dot(x)) * n


@ti.func
def bond_end_arms(p: ti.template(), bd: ti.template(), b, q):
    """Bond b's lever arms (bond_arms) seen from its end q: (q's, its neighbour's)."""
    ai, aj = bond_arms(p, bd, b)
    aq, ao = aj, ai
    if q == bd.i[b]:
        aq, ao = ai, aj
    return aq, ao


@ti.func
def bond_end(bd: ti.template(), b, q):
    """Bond b seen from its end q: sign s (+1 when q is its j), neighbour o, and the step's
    stiffness coefficients (alpha, beta) of K_b = (C_b + W_o)^-1."""
    s = 1.0
    o = bd.i[b]
    k4 = bd.stiff[b]
    alpha, beta = k4[2], k4[3]
    if q == bd.i[b]:
        s = -1.0
        o = bd.j[b]
        alpha, beta = k4[0], k4[1]
    return s, o, alpha, beta


@ti.func
def bond_residual(p: ti.template(), wl: ti.template(), bd: ti.template(), b, s):
    """Residual e = s (u + C R + rhs) of bond b seen from the end with sign s, at the current
    velocities and impulse."""
    n = bd.normal[b]
    r_imp = bd.impulse[b]
    rn = r_imp.dot(n)
    u = bond_relative_velocity(p, wl, bd, b)
    res = u + bd.cn[b] * rn * n + bd.ct[b] * (r_imp - rn * n) + bd.rhs_n[b] * n + bd.rhs_t[b]
    return s * res


@ti.func
def particle_bond_count(bd: ti.template(), q):
    """Bonds of particle q: those where it is i (bonds start[q]..) then those where it is j."""
    return (bd.start[q + 1] - bd.start[q]) + (bd.rev_start[q + 1] - bd.rev_start[q])


@ti.func
def particle_bond(bd: ti.template(), q, k):
    """The k-th bond of particle q (see particle_bond_count)."""
    nf = bd.start[q + 1] - bd.start[q]
    b = bd.start[q] + k
    if k >= nf:
        b = bd.rev[bd.rev_start[q] + k - nf]
    return b


@ti.func
def held_unknown(p: ti.template(), q, r: ti.template()):
    """1 when unknown r (0-2 velocity, 3-5 rotation) of particle q is held (infinite mass or
    inertia): its block row is the identity, its right side zero."""
    held = 0
    if ti.static(r < 3):
        if p.inv_mass[q] == 0.0:
            held = 1
    else:
        if p.inv_inertia[q] == 0.0:
            held = 1
    return held


@ti.func
def bonds_factor(p: ti.template(), bd: ti.template(), on):
    """Per step, after bonds_prepare: (alpha, beta) of each intact bond's ends (Bonds.stiff)
    and the inverse block matrix M' + sum G_b^T K_b G_b of each particle with intact bonds
    (Bonds.inverse; held unknowns get identity rows and columns). `on` (0 or 1, at run time:
    one compiled kernel for both): 0 does nothing."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for b in range(bd.total[None] * on):
        if bd.state[b] == INTACT:
            i, j = bd.i[b], bd.j[b]
            ai, aj = bond_arms(p, bd, b)
            # seen from i the neighbour is j, and the other way round
            bd.stiff[b] = ti.Vector([
                1.0 / (bd.cn[b] + p.inv_mass[j]),
                1.0 / (bd.ct[b] + p.inv_mass[j] + aj * aj * p.inv_inertia[j]),
                1.0 / (bd.cn[b] + p.inv_mass[i]),
                1.0 / (bd.ct[b] + p.inv_mass[i] + ai * ai * p.inv_inertia[i])])
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for q in range(p.count[None] * on):
        rq = p.radius[q]
        a = ti.Matrix.zero(float, 6, 6)
        count = 0
        for k in range(particle_bond_count(bd, q)):
            b = particle_bond(bd, q, k)
            if bd.state[b] == INTACT:
                count += 1
                n = bd.normal[b]
                s = 1.0
                o = bd.i[b]
                if q == bd.i[b]:
                    s = -1.0
                    o = bd.j[b]
                aq, ao = bond_end_arms(p, bd, b, q)
                alpha = 1.0 / (bd.cn[b] + p.inv_mass[o])
                beta = 1.0 / (bd.ct[b] + p.inv_mass[o] + ao * ao * p.inv_inertia[o])
                kb = (alpha - beta) * n.outer_product(n)
                for r in ti.static(range(3)):
                    kb[r, r] += beta
                # the unit offset of q's contact point, in units of r_q (rotations are
                # scaled by r_q): -s (a_q / r_q) n
                sk_ = skew(-s * (aq / rq) * n)
                ks = kb @ sk_
                sks = sk_.transpose() @ ks
                for r in ti.static(range(3)):
                    for c in ti.static(range(3)):
                        a[r, c] += kb[r, c]
                        a[r, 3 + c] -= ks[r, c]
                        a[3 + c, r] -= ks[r, c]
                        a[3 + r, 3 + c] += sks[r, c]
                # the frame's turn (solve_bond_turn) between the centres, on translation only
                kt = turn_stiffness(p, bd, b, o)
                if kt > 0.0:
                    for r in ti.static(range(3)):
                        for c in ti.static(range(3)):
                            a[r, c] += kt * ((1.0 if ti.static(r == c) else 0.0) - n[r] * n[c])
        if count > 0:
            if p.inv_mass[q] > 0.0:
                for r in ti.static(range(3)):
                    a[r, r] += 1.0 / p.inv_mass[q]
            if p.inv_inertia[q] > 0.0:
                for r in ti.static(range(3)):
                    a[3 + r, 3 + r] += 1.0 / (p.inv_inertia[q] * rq * rq)
            for r in ti.static(range(6)):
                if held_unknown(p, q, r) == 1:
                    for c in ti.static(range(6)):
                        a[r, c] = 0.0
                        a[c, r] = 0.0
                    a[r, r] = 1.0
            inv = cholesky_inverse6(a)
            f = ti.Vector.zero(float, 21)
            for e in ti.static(range(21)):
                f[e] = inv[TRI6[e][0], TRI6[e][1]]
            bd.inverse[q] = f


@ti.func
def skew(a):
    return ti.Matrix([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


@ti.func
def block_inverse_apply(bd: ti.template(), q, g):
    """xi = A^-1 g with particle q's stored symmetric block inverse."""
    f = bd.inverse[q]
    xi = ti.Vector.zero(float, 6)
    for e in ti.static(range(21)):
        r, c = ti.static(TRI6[e][0], TRI6[e][1])
        xi[r] += f[e] * g[c]
        if ti.static(r != c):
            xi[c] += f[e] * g[r]
    return xi


@ti.func
def solve_particle_bonds(p: ti.template(), wl: ti.template(), bd: ti.template(), q,
                         measure: ti.template()):
    """Exact solve of the intact bonds of particle q (the star of q and its bonded
    neighbours, see above) with the step's stiffnesses and block inverse (bonds_factor). A
    fixed particle (or locked rotation) keeps those unknowns at zero: its bonds are then solved
    one by one. Returns (sum |dR_b|, sum |R_b|) over its intact bonds when `measure` (static)
    is 1 (the coloured schedule's residual), else zeros."""
    rq = p.radius[q]
    dsum = 0.0
    rsum = 0.0
    g = ti.Vector.zero(float, 6)
    count = 0
    nq = particle_bond_count(bd, q)
    for k in range(nq):
        b = particle_bond(bd, q, k)
        if bd.state[b] == INTACT:
            count += 1
            s, o, alpha, beta = bond_end(bd, b, q)
            aq, _ao = bond_end_arms(p, bd, b, q)
            n = bd.normal[b]
            e = bond_residual(p, wl, bd, b, s)
            bd.resid[b] = e
            ke = stiffness_apply(alpha, beta, n, e)
            # G_b^T K_b e_b: the force K e and its moment about q's centre, a x K e with the
            # offset a = -s (a_q / r_q) n (rotations scaled by r_q)
            ske = -s * (aq / rq) * n.cross(ke)
            for r in ti.static(range(3)):
                g[r] -= ke[r]
                g[3 + r] -= ske[r]
            if bd.turn_on[None] == 1:
                qd = turn_block_impulse(p, bd, b, q, o, s, ti.Vector([0.0, 0.0, 0.0]))
                for r in ti.static(range(3)):
                    g[r] += qd[r]
    if count > 0:
        for r in ti.static(range(6)):
            if held_unknown(p, q, r) == 1:
                g[r] = 0.0
        xi = block_inverse_apply(bd, q, g)
        dv = ti.Vector([xi[0], xi[1], xi[2]])
        dw = ti.Vector([xi[3], xi[4], xi[5]])
        sum_q = ti.Vector([0.0, 0.0, 0.0])
        sum_t = ti.Vector([0.0, 0.0, 0.0])
        for k in range(nq):
            b = particle_bond(bd, q, k)
            if bd.state[b] == INTACT:
                s, o, alpha, beta = bond_end(bd, b, q)
                aq, ao = bond_end_arms(p, bd, b, q)
                lam = aq / rq
                n = bd.normal[b]
                e = bd.resid[b]
                # e + G_b xi = e + dv - a x dw with a = -s (a_q / r_q) n
                qb = -stiffness_apply(alpha, beta, n, e + dv + (s * lam) * n.cross(dw))
                if bd.turn_on[None] == 1:
                    # the turn's impulse received by q (read before o moves)
                    qd = turn_block_impulse(p, bd, b, q, o, s, dv)
                    bd.turn[b] += s * qd
                    sum_q += qd
                    p.v[o] = p.v[o] - qd * p.inv_mass[o]
                bd.impulse[b] += s * qb
                if ti.static(measure == 1):
                    dsum += qb.norm()
                    rsum += bd.impulse[b].norm()
                sum_q += qb
                sum_t -= (s * lam) * n.cross(qb)
                # the neighbour receives -Q_b at its contact point s a_o n
                # (-a_j n when it is j, +a_i n when it is i)
                ro = s * ao * n
                p.v[o] = p.v[o] - qb * p.inv_mass[o]
                p.w[o] = p.w[o] - p.inv_inertia[o] * ro.cross(qb)
        p.v[q] = p.v[q] + sum_q * p.inv_mass[q]
        p.w[q] = p.w[q] + (p.inv_inertia[q] * rq) * sum_t
    return dsum, rsum


@ti.func
def turn_stiffness(p: ti.template(), bd: ti.template(), b, o):
    """The stiffness kappa / (1 + kappa m_o^-1) of bond b's turn (solve_bond_turn) seen from
    the end whose neighbour is o (0 when off, or in compression)."""
    kd = turn_coefficient(bd, b)
    return kd / (1.0 + kd * p.inv_mass[o])


@ti.func
def turn_block_impulse(p: ti.template(), bd: ti.template(), b, q, o, s, dv):
    """The impulse bond b's turn gives its end q (sign s, neighbour o) in q's block solve when
    q's velocity changes by dv: -K (e + P dv), e = P (v_q - v_o) + s G / kappa its residual
    (zero when G = -kappa P (v_j - v_i)), K = turn_stiffness; zero when off or in compression."""
    out = ti.Vector([0.0, 0.0, 0.0])
    kd = turn_coefficient(bd, b)
    if kd > 0.0:
        n = bd.normal[b]
        d = p.v[q] - p.v[o] + dv
        out = -turn_stiffness(p, bd, b, o) * ((d - d.dot(n) * n) + (s / kd) * bd.turn[b])
    return out


# --- pieces of a sweep shared by the serial and partitioned schedules ---------------------------
@ti.func
def bond_sweep_change(bd: ti.template(), b):
    """Bond b's impulse change over the sweep, against the snapshot in acc_d (which it
    replaces, for the momentum): (|dR|^2, |dR|, |R|)."""
    r_new = bd.impulse[b]
    dr = r_new - bd.acc_d[b]
    bd.acc_d[b] = dr
    return dr.dot(dr), dr.norm(), r_new.norm()


@ti.func
def visit_contact(p: ti.template(), wl: ti.template(), ct: ti.template(), k, n_part, measure,
                  accel: ti.template()):
    """One Gauss-Seidel visit of contact k: (|dR|^2 (NNCG only: dR kept as the search
    direction), |dR| and |R| (only when `measure`, else 0))."""
    dr, r_new = solve_contact_dr(p, wl, ct, k, n_part)
    d2 = 0.0
    da = 0.0
    ra = 0.0
    if ti.static(accel == 1):
        ct.acc_d[k] = dr
        d2 = dr.dot(dr)
    if measure == 1:
        da = dr.norm()
        ra = r_new.norm()
    return d2, da, ra


@ti.func
def nncg_beta(g2, g2_prev, sweeps):
    """NNCG momentum factor |g_k|^2 / |g_k-1|^2 after `sweeps` sweeps; 0 (a restart) after the
    first sweep or when it exceeds 1."""
    beta = 0.0
    if g2_prev > 0.0:
        beta = g2 / g2_prev
    if beta > 1.0 or sweeps == 1:
        beta = 0.0
    return beta


@ti.func
def body_sweep_start(p: ti.template(), cs: ti.template(), i):
    """Particle i's velocities at the start of a sweep, for body_momentum."""
    cs.sweep_v[i] = p.v[i]
    cs.sweep_w[i] = p.w[i]


@ti.func
def body_momentum(p: ti.template(), cs: ti.template(), i, beta):
    """The NNCG momentum of particle i, from its own velocities: what the momentum of its
    items (bond_momentum, contact_momentum: R += beta p) gives it, without visiting them.
    Velocities are linear in the impulses, v = v_free + M^-1 H^T R, and a sweep changes them
    only through its items' impulses, so the sweep's change of v is M^-1 H^T g (g the
    impulse changes over the sweep), and the body part of each item's direction
    p = beta p + g is u = M^-1 H^T p, kept per body as u = beta u + (v - v at the sweep's
    start). The momentum moves the body by beta u_prev, the sum of its items' beta M^-1 H^T p
    (exact but for rounding; kinematic bodies never change velocity, so they get none). Then
    the next sweep's start."""
    dv = p.v[i] - cs.sweep_v[i]
    dw = p.w[i] - cs.sweep_w[i]
    if beta > 0.0:
        uv = beta * cs.dir_v[i]
        uw = beta * cs.dir_w[i]
        p.v[i] = p.v[i] + uv
        p.w[i] = p.w[i] + uw
        dv += uv
        dw += uw
    cs.dir_v[i] = dv
    cs.dir_w[i] = dw
    body_sweep_start(p, cs, i)


@ti.func
def bond_momentum(p: ti.template(), bd: ti.template(), b, beta, bodies: ti.template()):
    """NNCG momentum of intact bond b: R += beta p, p = beta p + dR; `bodies` (static) 1 applies
    it to its bodies too, 0 leaves them to body_momentum."""
    if bd.state[b] == INTACT:
        pb = bd.acc_p[b]
        if beta > 0.0:
            dr = beta * pb
            bd.impulse[b] += dr
            if ti.static(bodies == 1):
                apply_bond_impulse(p, bd, b, dr)
        bd.acc_p[b] = beta * pb + bd.acc_d[b]


@ti.func
def contact_momentum(p: ti.template(), ct: ti.template(), k, beta, bodies: ti.template()):
    """NNCG momentum of contact k (none on a pair of kinematic bodies); `bodies` as
    bond_momentum's."""
    pk = ct.acc_p[k]
    moves = 1
    if ti.static(OPEN_SKIP):
        # a zero direction (a contact that stayed open) moves nothing
        if pk[0] == 0.0 and pk[1] == 0.0 and pk[2] == 0.0:
            moves = 0
    if beta > 0.0 and ct.wnn[k] > 0.0 and moves == 1:
        dr = beta * pk
        ct.impulse[k] += dr
        if ti.static(bodies == 1):
            apply_impulse(p, ct.i[k], ct.j[k], ct.normal[k], dr)
    ct.acc_p[k] = beta * pk + ct.acc_d[k]


# --- step kernels ------------------------------------------------------------------------------
@ti.func
def predict(p: ti.template(), h: ti.template(), gx: ti.template(), gy: ti.template(),
            gz: ti.template()):
    """Keep the beginning-of-step velocities; add the impulse of external forces.
    (g is built inside the loop: a vector of f64 set before the parallel loop is handed to it
    through Taichi's global temporaries, misaligned on CUDA: CUDA_ERROR_MISALIGNED_ADDRESS.)"""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(p.count[None]):
        g = ti.Vector([gx, gy, gz])
        p.v_old[i] = p.v[i]
        p.w_old[i] = p.w[i]
        if p.inv_mass[i] > 0.0:
            p.v[i] += h * (g + p.f_ext[i] * p.inv_mass[i])


@ti.func
def _apply_warm_start(p: ti.template(), ct: ti.template(), bd: ti.template(), on):
    """The bonds' and contacts' impulses applied to the bodies; `on` 0 (at run time) skips it."""
    ti.loop_config(serialize=True)
    for b in range(bd.total[None] * on):
        if bd.state[b] == INTACT:
            apply_bond_impulse(p, bd, b, bd.impulse[b])
    ti.loop_config(serialize=True)
    for k in range(ct.total[None] * on):
        apply_impulse(p, ct.i[k], ct.j[k], ct.normal[k], ct.impulse[k])


@ti.kernel
def apply_warm_start(p: ti.template(), ct: ti.template(), bd: ti.template()):
    _apply_warm_start(p, ct, bd, 1)


@ti.func
def gather_system_stats(p: ti.template(), st: ti.template()):
    """Over the batched systems: the most sweeps and the largest residual (fixed order)."""
    sweeps = 0
    residual = 0.0
    for sy in range(p.systems[None]):
        sweeps = ti.max(sweeps, st.sys_sweeps[sy])
        residual = ti.max(residual, st.sys_residual[sy])
    st.sweeps[None] = sweeps
    st.residual[None] = residual


@ti.kernel
def nlgs_serial(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
                st: ti.template(), max_sweeps: ti.i32, tol: float, check_every: ti.i32,
                symmetric: ti.i32, accel: ti.template(), blocks: ti.template(),
                quad: ti.template()):
    """All sweeps of one step in one launch. `symmetric`: 0 every sweep forward (item
    order), 1 forward and backward sweeps alternate. `quad` (static): 0 the convergence
    measure is the sweep's relative impulse change, 1 LMGC90's 'Quad ' check (a pass over
    the system's items that updates nothing, quad_check_range). `accel` (static): 0 plain Gauss-Seidel;
    1 nonsmooth nonlinear conjugate gradient (NNCG, Silcowitz, Niebe & Erleben 2010): each
    sweep's change g_k is used as a descent direction and the impulses get the momentum
    beta p_{k-1}, beta = |g_k|^2 / |g_{k-1}|^2, restarted (p = g) when beta > 1. The momentum
    is applied to the bodies at once (one extra pass over the items), so velocities always
    equal v_free + M^-1 H^T R. (The resident schedule moves the bodies from their own
    velocities instead, body_momentum; tried here, that gained nothing: 2.02e-5 against
    1.95e-5 s per particle-step on the seed-1 shear, 0.02 s.) The step ends after a plain
    sweep, never after a momentum pass, so the final impulses satisfy the contact law.
    `blocks` (static): 1 relaxes the bonds particle by particle (solve_particle_bonds), 0 bond
    by bond.

    Batched systems (p.systems > 1) share no body, so the outer loop over systems is parallel
    (one thread per system) and each system sweeps its own contiguous particles, bonds and
    contacts until its own convergence: its numbers are those it would have alone."""
    # Taichi's CPU runtime runs a parallel loop of a few iterations on one thread (measured:
    # 2 or 64 iterations take as long as serially, 1024 split over the cores), so the
    # systems are spread over SYSTEM_SPREAD iterations each, all but the first empty
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for t in range(p.systems[None] * SYSTEM_SPREAD):
        if t % SYSTEM_SPREAD == 0:
            sy = t // SYSTEM_SPREAD
            q0, q1 = p.sys_start[sy], p.sys_start[sy + 1]
            b0, b1 = bd.start[q0], bd.start[q1]
            c0, c1 = ct.start[q0], ct.start[q1]
            sweeps = 0
            residual = 0.0
            done = 0
            n_part = p.count[None]
            g2_prev = 0.0
            while done == 0:
                dsum = 0.0
                rsum = 0.0
                g2 = 0.0
                measure = 0
                if ti.static(quad == 0):
                    if (sweeps + 1) % check_every == 0 or sweeps + 1 >= max_sweeps:
                        measure = 1
                # symmetric Gauss-Seidel: forward sweeps alternate with backward ones (on a
                # shear it needs more sweeps than forward ones alone: 34.4 against 25.0)
                backward = 0
                if symmetric == 1:
                    backward = sweeps % 2
                if ti.static(blocks == 1):
                    if b1 > b0:
                        for b in range(b0, b1):
                            bd.acc_d[b] = bd.impulse[b]
                        for qq in range(q0, q1):
                            q = qq
                            if backward == 1:
                                q = q1 - 1 - (qq - q0)
                            solve_particle_bonds(p, wl, bd, q, 0)
                        for b in range(b0, b1):
                            if bd.state[b] == INTACT:
                                d2, da, ra = bond_sweep_change(bd, b)
                                if ti.static(accel == 1):
                                    g2 += d2
                                dsum += da
                                rsum += ra
                else:
                    for bb in range(b0, b1):
                        b = bb
                        if backward == 1:
                            b = b1 - 1 - (bb - b0)
                        dr, r_new = solve_bond_dr(p, wl, bd, b)
                        if ti.static(accel == 1):
                            bd.acc_d[b] = dr
                            g2 += dr.dot(dr)
                        dsum += dr.norm()
                        rsum += r_new.norm()
                for kk in range(c0, c1):
                    k = kk
                    if backward == 1:
                        k = c1 - 1 - (kk - c0)
                    d2, da, ra = visit_contact(p, wl, ct, k, n_part, measure, accel)
                    if ti.static(accel == 1):
                        g2 += d2
                    if measure == 1:
                        dsum += da
                        rsum += ra
                sweeps += 1
                if sweeps % check_every == 0 or sweeps >= max_sweeps:
                    residual = 0.0
                    if ti.static(quad == 1):
                        residual = quad_check_range(p, wl, ct, bd, b0, b1, c0, c1)
                    else:
                        residual = impulse_residual(dsum, rsum)
                    if residual <= tol or sweeps >= max_sweeps:
                        done = 1
                if ti.static(accel == 1):
                    if done == 0:
                        beta = nncg_beta(g2, g2_prev, sweeps)
                        for b in range(b0, b1):
                            bond_momentum(p, bd, b, beta, 1)
                        for k in range(c0, c1):
                            contact_momentum(p, ct, k, beta, 1)
                    g2_prev = g2
            st.sys_sweeps[sy] = sweeps
            st.sys_residual[sy] = residual
    ti.loop_config(serialize=True)
    for _ in range(1):
        gather_system_stats(p, st)


@ti.func
def item_bodies(ct: ti.template(), bd: ti.template(), q, nb):
    """Bodies (i, j) of item q (q < nb: bond q, else contact q - nb) and 1 if it is active
    (broken bonds are not)."""
    i = 0
    j = 0
    active = 1
    if q < nb:
        i, j = bd.i[q], bd.j[q]
        if bd.state[q] != INTACT:
            active = 0
    else:
        i, j = ct.i[q - nb], ct.j[q - nb]
    return i, j, active


# --- colouring for the parallel schedule -------------------------------------------------------
@ti.func
def block_mask(bd: ti.template(), cs: ti.template(), q, w):
    """Colours (word w) used by the bodies of particle q's bond block: q and its intact
    bonded neighbours; and the number of those bonds."""
    used = cs.mask[q, w]
    count = 0
    for k in range(particle_bond_count(bd, q)):
        b = particle_bond(bd, q, k)
        if bd.state[b] == INTACT:
            count += 1
            used |= cs.mask[bd.i[b] + bd.j[b] - q, w]
    return used, count


@ti.func
def block_mark(bd: ti.template(), cs: ti.template(), q, w, bit):
    cs.mask[q, w] |= ti.u32(1) << ti.u32(bit)
    for k in range(particle_bond_count(bd, q)):
        b = particle_bond(bd, q, k)
        if bd.state[b] == INTACT:
            o = bd.i[b] + bd.j[b] - q
            cs.mask[o, w] |= ti.u32(1) << ti.u32(bit)


@ti.kernel
def colour_greedy(n: ti.i32, p: ti.template(), ct: ti.template(), bd: ti.template(),
                  cs: ti.template(), st: ti.template(), blocks: ti.template()):
    """Greedy colouring of the bond items (first, so they always get the same colours) then
    the contacts, in canonical order. `blocks` (static) 0: item q < nb is bond q; 1: item
    q < n is the bond block of particle q (solve_particle_bonds: q and all its bonded
    neighbours are its bodies, so one colour holds blocks two bonds apart at least). Then
    contact q - nb (nb = n with blocks). A counting sort lists the items colour by colour in
    `cs.order` (CSR `cs.start`), inside a colour system by system (CSR `cs.sys_start`), and
    in canonical order inside a system. Broken bonds and particles without intact bonds get
    colour -1 and are left out. Sets st.colours, st.colour_overflow."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(n):
        for w in ti.static(range(COLOUR_WORDS)):
            cs.mask[i, w] = ti.u32(0)
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range(MAX_COLOURS + 1):
        cs.start[c] = 0
    nb = bd.total[None]
    if ti.static(blocks == 1):
        nb = n
    nc = ct.total[None]
    ncol = 0
    overflow = 0
    ti.loop_config(serialize=True)
    for q in range(nb + nc):
        i, j, active = 0, 0, 1
        if ti.static(blocks == 1):
            if q < nb:
                i = q
                _, count = block_mask(bd, cs, q, 0)
                if count == 0:
                    active = 0
            else:
                i, j = ct.i[q - nb], ct.j[q - nb]
        else:
            i, j, active = item_bodies(ct, bd, q, nb)
        col = -1
        if active == 1:
            for w in range(COLOUR_WORDS):
                if col < 0:
                    used = ti.u32(0)
                    is_block = 0
                    if ti.static(blocks == 1):
                        if q < nb:
                            is_block = 1
                    if is_block == 1:
                        used, _ = block_mask(bd, cs, q, w)
                    else:
                        used = cs.mask[i, w]
                        if j < n:
                            used |= cs.mask[j, w]
                    if used != ti.u32(0xFFFFFFFF):
                        bit = 0
                        while ((used >> ti.u32(bit)) & ti.u32(1)) == ti.u32(1):
                            bit += 1
                        col = w * 32 + bit
                        if is_block == 1:
                            block_mark(bd, cs, q, w, bit)
                        else:
                            cs.mask[i, w] |= ti.u32(1) << ti.u32(bit)
                            if j < n:
                                cs.mask[j, w] |= ti.u32(1) << ti.u32(bit)
            if col < 0:
                overflow = 1
                col = 0
            ncol = ti.max(ncol, col + 1)
            cs.start[col + 1] += 1
        cs.item_colour[q] = col
        cs.change[q] = ti.Vector([0.0, 0.0])
    ti.loop_config(serialize=True)
    for c in range(MAX_COLOURS):
        cs.start[c + 1] += cs.start[c]
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range(MAX_COLOURS):
        cs.cursor[c] = cs.start[c]
    ti.loop_config(serialize=True)
    for _ in range(1):
        nsys = p.systems[None]
        for sy in range(nsys):
            for c in range(ncol):
                cs.sys_start[c * nsys + sy] = cs.cursor[c]
            qb0, qb1, qc0, qc1 = system_items(p, ct, bd, sy, blocks)
            for v in range(qb1 - qb0 + qc1 - qc0):
                q = listed_item(v, qb1 - qb0, qb0, qc0)
                c = cs.item_colour[q]
                if c >= 0:
                    cs.order[cs.cursor[c]] = q
                    cs.cursor[c] += 1
        cs.sys_start[ncol * nsys] = cs.start[ncol]
    st.colours[None] = ncol
    st.colour_overflow[None] = overflow


@ti.kernel
def solve_colours(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
                  cs: ti.template(), base: ti.i32, blocks: ti.template(), k: ti.template()):
    """Colours base .. base + k - 1 one after the other, each colour's items at once (they
    share no dynamic body), in ONE kernel call
    (k parallel loops unrolled: one Python launch instead of k, whose overhead, about 50 us a
    call, dominated the GPU's sweeps; a colour past the last one is an empty range). Same
    numbers as solve_colour colour by colour. Compile time grows faster than k (CPU, particle
    blocks: 4 s for k = 4, 13 s for 8, 48 s for 16)."""
    for c in ti.static(range(k)):
        ti.loop_config(serialize=ti.static(backend.serial_loops()))
        for s in range(cs.start[ti.min(base + c, MAX_COLOURS)],
                       cs.start[ti.min(base + c + 1, MAX_COLOURS)]):
            solve_item(p, wl, ct, bd, cs, s, blocks, 0)


@ti.kernel
def solve_colours_next(p: ti.template(), wl: ti.template(), ct: ti.template(),
                       bd: ti.template(), cs: ti.template(), blocks: ti.template(),
                       k: ti.template()):
    """solve_colours with its first colour read from cs.base instead of a runtime argument,
    and cs.base advanced by k (back to 0 after the last of the cs.ncol colours, so a sweep is
    ceil(ncol / k) calls and the next sweep starts at colour 0). A call without a runtime
    argument has no argument buffer for a GPU launch to copy from host memory (CUDA may wait
    for the stream before such a copy). Same numbers as solve_colours."""
    for c in ti.static(range(k)):
        ti.loop_config(serialize=ti.static(backend.serial_loops()))
        for s in range(cs.start[ti.min(cs.base[None] + c, MAX_COLOURS)],
                       cs.start[ti.min(cs.base[None] + c + 1, MAX_COLOURS)]):
            solve_item(p, wl, ct, bd, cs, s, blocks, 0)
    ti.loop_config(serialize=True)
    for _ in range(1):
        nxt = cs.base[None] + k
        if nxt >= cs.ncol[None]:
            nxt = 0
        cs.base[None] = nxt


@ti.func
def solve_item(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
               cs: ti.template(), s, blocks: ti.template(), accel: ti.template()):
    """The local solve of the item at position s of the colour lists; its (|dR|, |R|) into
    cs.change. `accel` (static) >= 1: a contact also keeps its dR in acc_d (NNCG's direction:
    a contact is visited once per sweep, so that is its change over the sweep)."""
    nb = bd.total[None]
    if ti.static(blocks == 1):
        nb = p.count[None]
    q = cs.order[s]
    da = 0.0
    ra = 0.0
    if q < nb:
        if ti.static(blocks == 1):
            da, ra = solve_particle_bonds(p, wl, bd, q, 1)
        else:
            da, ra = solve_bond(p, wl, bd, q)
    else:
        if ti.static(accel >= 1):
            dr, r_new = solve_contact_dr(p, wl, ct, q - nb, p.count[None])
            ct.acc_d[q - nb] = dr
            da, ra = dr.norm(), r_new.norm()
        else:
            da, ra = solve_contact(p, wl, ct, q - nb, p.count[None], 1)
    cs.change[q] = ti.Vector([da, ra])


@ti.func
def listed_item(v, n1, qb0, qc0):
    """The v-th item of a list of bond items qb0 .. qb0 + n1 - 1, then contacts from item qc0
    (a system's items: system_items)."""
    q = qb0 + v
    if v >= n1:
        q = qc0 + v - n1
    return q


@ti.func
def change_chunk(cs: ti.template(), ch, nitems, n1, qb0, qc0):
    """(sum |dR|, sum |R|) of the last sweep over chunk ch (RESIDUAL_CHUNK items, in order) of
    a list of `nitems` items: the v-th is item qb0 + v for v < n1, else item qc0 + v - n1 (a
    system's bond items, then its contacts; for all the items: n1 = nitems, qb0 = 0)."""
    d = 0.0
    r = 0.0
    for v in range(ch * RESIDUAL_CHUNK, ti.min(nitems, (ch + 1) * RESIDUAL_CHUNK)):
        q = listed_item(v, n1, qb0, qc0)
        d += cs.change[q][0]
        r += cs.change[q][1]
    return ti.Vector([d, r])


@ti.func
def partials_residual(cs: ti.template(), base, nchunks):
    """impulse_residual of the chunk partials cs.partial[base .. base + nchunks - 1], summed in
    chunk order."""
    d = 0.0
    r = 0.0
    for k in range(nchunks):
        d += cs.partial[base + k][0]
        r += cs.partial[base + k][1]
    return impulse_residual(d, r)


@ti.kernel
def sweep_residual(cs: ti.template(), count: ti.i32) -> float:
    """Relative impulse change of the last sweep: partial sums over fixed chunks of
    RESIDUAL_CHUNK items in item order (in parallel), then the partials in chunk order
    (deterministic: the same sums in the same order whatever the thread timing).
    Not the serial schedule's figure where bonds are relaxed in particle blocks: each bond is
    counted at both of its ends' visits, |dR| per visit and |R| twice, where the serial and
    partitioned sweeps take one |dR| over the sweep; for a bond whose two visits push the same
    way, that is about half the serial figure (helper review, session 32). The 'Quad ' check
    (convergence = "quad") counts each bond once in every schedule."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range((count + RESIDUAL_CHUNK - 1) // RESIDUAL_CHUNK):
        cs.partial[c] = change_chunk(cs, c, count, count, 0, 0)
    ti.loop_config(serialize=True)
    for _ in range(1):
        cs.residual[None] = partials_residual(cs, 0, (count + RESIDUAL_CHUNK - 1) // RESIDUAL_CHUNK)
    return cs.residual[None]


# --- the resident schedule: all sweeps of a step in one launch -------------------------------------
# A GPU thread block per system runs the whole step: the colours one after the other, each
# colour's items of its system strided over the block's threads, a block barrier after each
# colour and around the convergence test. Its threads share one decision to go on or stop,
# read after a barrier, so every thread meets every barrier. On the CPU a block is one thread
# (Taichi's CPU loops have no barrier), which is the coloured schedule's sweep done in order.
RESIDENT_THREADS = 256      # threads per block on a GPU (f64 local solves: registers per thread)


def resident_gpu_threads(text: str | None = None) -> int:
    """Threads per block of solve_resident on a GPU: RESIDENT_THREADS, or the environment
    variable TCD_RESIDENT_THREADS (a multiple of 32 from 32 to 1024), for measuring the block
    size on a device (each value compiles its own kernel; the numbers are the same for any:
    a colour's items share no body, and the sums go chunk by chunk in chunk order)."""
    text = os.environ.get("TCD_RESIDENT_THREADS", "") if text is None else text
    if not text:
        return RESIDENT_THREADS
    try:
        k = int(text)
    except ValueError:
        k = 0
    if not (32 <= k <= 1024 and k % 32 == 0):
        raise ValueError(f"TCD_RESIDENT_THREADS={text!r}: expected a multiple of 32 from 32 "
                         "to 1024 (threads per GPU block)")
    return k


RESIDENT_MOMENTUM = {"bodies": 2, "items": 1}


def resident_momentum(text: str | None = None) -> int:
    """solve_resident's `accel` for NNCG: 2, the momentum of the bodies from their own
    velocities (body_momentum; the default), or with the environment variable
    TCD_RESIDENT_MOMENTUM=items 1, session 37's pass over the colours, for measuring the two
    on a device (the same sweeps but for rounding)."""
    text = os.environ.get("TCD_RESIDENT_MOMENTUM", "") if text is None else text
    if not text:
        return RESIDENT_MOMENTUM["bodies"]
    if text not in RESIDENT_MOMENTUM:
        raise ValueError(f"TCD_RESIDENT_MOMENTUM={text!r}: expected one of "
                         f"{', '.join(RESIDENT_MOMENTUM)}")
    return RESIDENT_MOMENTUM[text]


def resident_threads() -> int:
    """Threads per system of solve_resident on the running backend (one on the CPU, whose
    loops have no barrier)."""
    return 1 if backend.arch() == "cpu" else resident_gpu_threads()


def resident_spread() -> int:
    """Loop iterations per system of solve_resident: its threads on a GPU; on the CPU
    SYSTEM_SPREAD, all but the first empty, so that a batch's systems go to the pool's threads
    (Taichi's CPU runtime runs a loop of a few iterations on one thread: nlgs_serial)."""
    return SYSTEM_SPREAD if backend.arch() == "cpu" else resident_gpu_threads()


@ti.func
def resident_barrier(threads: ti.template()):
    if ti.static(threads > 1):
        ti.simt.block.sync()


@ti.func
def system_items(p: ti.template(), ct: ti.template(), bd: ti.template(), sy,
                 blocks: ti.template()):
    """System sy's items: bond items qb0 .. qb1 - 1 (its bonds, or with blocks its particles'
    blocks), then contacts as items qc0 .. qc1 - 1 (contact q - nb, nb the bond items)."""
    q0, q1 = p.sys_start[sy], p.sys_start[sy + 1]
    nb = bd.total[None]
    qb0, qb1 = bd.start[q0], bd.start[q1]
    if ti.static(blocks == 1):
        nb = p.count[None]
        qb0, qb1 = q0, q1
    return qb0, qb1, nb + ct.start[q0], nb + ct.start[q1]


@ti.func
def item_system(p: ti.template(), ct: ti.template(), bd: ti.template(), q, nb,
                blocks: ti.template()):
    """The batched system of item q (bond item q < nb, else contact q - nb)."""
    i = 0
    if q < nb:
        if ti.static(blocks == 1):
            i = q
        else:
            i = bd.i[q]
    else:
        i = ct.i[q - nb]
    return p.system[i]


@ti.func
def item_sweep_change(ct: ti.template(), bd: ti.template(), cs: ti.template(), q, nb,
                      blocks: ti.template()):
    """sum |dR|^2 of item q over the sweep (NNCG): a particle block counts the bonds whose
    first end is its particle (each bond once), an intact bond itself, dR against the snapshot
    in acc_d, which it replaces by dR (the direction); a contact its visit's |dR|^2 (its dR is
    in acc_d already: solve_item)."""
    g2 = 0.0
    if q < nb:
        if ti.static(blocks == 1):
            for e in range(bd.start[q], bd.start[q + 1]):
                if bd.state[e] == INTACT:
                    d2, _, _ = bond_sweep_change(bd, e)
                    g2 += d2
        elif bd.state[q] == INTACT:
            d2, _, _ = bond_sweep_change(bd, q)
            g2 += d2
    else:
        g2 = cs.change[q][0] * cs.change[q][0]
    return g2


@ti.func
def bond_item_snapshot(bd: ti.template(), q, blocks: ti.template()):
    """The impulses of bond item q (a particle block: the bonds whose first end is its
    particle) into acc_d: the start of the next sweep, for item_sweep_change."""
    if ti.static(blocks == 1):
        for e in range(bd.start[q], bd.start[q + 1]):
            bd.acc_d[e] = bd.impulse[e]
    else:
        bd.acc_d[q] = bd.impulse[q]


@ti.func
def item_momentum(p: ti.template(), ct: ti.template(), bd: ti.template(), q, nb, beta,
                  blocks: ti.template(), bodies: ti.template()):
    """NNCG momentum of item q (a particle block: the bonds whose first end is its particle,
    all among its bodies); then a bond item's snapshot for the next sweep. `bodies` (static)
    1: the item moves its bodies too; 0: its impulses only (body_momentum moves the bodies)."""
    if q < nb:
        if ti.static(blocks == 1):
            for e in range(bd.start[q], bd.start[q + 1]):
                bond_momentum(p, bd, e, beta, bodies)
        else:
            bond_momentum(p, bd, q, beta, bodies)
        bond_item_snapshot(bd, q, blocks)
    else:
        contact_momentum(p, ct, q - nb, beta, bodies)


@ti.kernel
def solve_resident(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
                   cs: ti.template(), st: ti.template(), ncol: ti.i32, max_sweeps: ti.i32,
                   tol: float, check_every: ti.i32, accel: ti.template(),
                   blocks: ti.template(), threads: ti.template(), spread: ti.template()):
    """All sweeps of one step over the colours of `cs` (solve_item, as solve_colours), one
    block of `threads` threads per system, each system to its own convergence (as
    nlgs_serial: a system's numbers are those it would have alone). The residual is
    sweep_residual's, over the system's items (its bond items, then its contacts) in chunks of
    RESIDUAL_CHUNK, summed in chunk order: for one system, with `accel` 0, the coloured
    schedule's numbers. A block reads its own system's items of each colour only
    (cs.sys_start). The colours are swept forward: reversing them on every second sweep took
    more sweeps (seed-1 shear, 0.02 s: 91.6 mean sweeps against 70.3 plain, 56.8 against 28.5
    with NNCG). `accel` (static) 1 or 2: NNCG as nlgs_serial's (the sweep's changes |dR|^2,
    summed by chunks of MOMENTUM_CHUNK items, then groups of chunks, each in order, give the
    momentum factor; never after the last sweep), with the
    bonds' snapshot for the next sweep (a contact's dR is kept by its visit). The momentum:
    with 2, one pass over the system's items (their impulses) and one over its particles
    (body_momentum), no colours; with 1 (session 37's) a pass over the colours, each item
    moving its impulses and bodies together (resident_momentum).
    Per system: sweeps and residual into st.sys_sweeps / st.sys_residual, then the largest
    into st.sweeps / st.residual. `spread` loop iterations per system, the first `threads` of
    them its block's threads (resident_threads, resident_spread)."""
    ti.loop_config(block_dim=spread, serialize=ti.static(backend.serial_loops()))
    for t in range(p.systems[None] * spread):
        sy = t // spread
        tid = t % spread
        if tid >= threads:
            continue
        nsys = p.systems[None]
        nb = bond_items(p.count[None], bd, blocks)
        qb0, qb1, qc0, qc1 = system_items(p, ct, bd, sy, blocks)
        n1 = qb1 - qb0
        nitems = n1 + qc1 - qc0
        nchunks = (nitems + RESIDUAL_CHUNK - 1) // RESIDUAL_CHUNK
        # this system's chunk partials in cs.partial: at most floor(earlier items / chunk)
        # + (earlier systems) chunks come before them
        base = (qb0 + qc0 - nb) // RESIDUAL_CHUNK + sy
        # the same for the momentum's chunks (cs.gpartial)
        ngchunks = (nitems + MOMENTUM_CHUNK - 1) // MOMENTUM_CHUNK
        gbase = (qb0 + qc0 - nb) // MOMENTUM_CHUNK + sy
        per_group = (ngchunks + MOMENTUM_GROUPS - 1) // MOMENTUM_GROUPS
        q0, q1 = p.sys_start[sy], p.sys_start[sy + 1]
        if ti.static(accel >= 1):
            # the first sweep's snapshot of the bonds (a contact keeps its visit's dR), and
            # with body_momentum of the bodies' velocities
            v = tid
            while v < n1:
                bond_item_snapshot(bd, qb0 + v, blocks)
                v += threads
            if ti.static(accel == 2):
                i = q0 + tid
                while i < q1:
                    body_sweep_start(p, cs, i)
                    i += threads
            resident_barrier(threads)
        sweeps = 0
        residual = 0.0
        g2_prev = 0.0           # thread 0's: the last sweep's sum |dR|^2
        done = 0
        while done == 0:
            for c in range(ncol):
                s = cs.sys_start[c * nsys + sy] + tid
                end = cs.sys_start[c * nsys + sy + 1]
                while s < end:
                    solve_item(p, wl, ct, bd, cs, s, blocks, accel)
                    s += threads
                resident_barrier(threads)
            sweeps += 1
            check = 0
            if sweeps % check_every == 0 or sweeps >= max_sweeps:
                check = 1
            sums = check
            if ti.static(accel >= 1):
                sums = 1
            if sums == 1:
                if check == 1:
                    ch = tid
                    while ch < nchunks:
                        cs.partial[base + ch] = change_chunk(cs, ch, nitems, n1, qb0, qc0)
                        ch += threads
                if ti.static(accel >= 1):
                    # |dR|^2 by chunks of MOMENTUM_CHUNK items, then MOMENTUM_GROUPS groups of
                    # consecutive chunks, each summed in order (then thread 0 sums the groups)
                    ch = tid
                    while ch < ngchunks:
                        g2 = 0.0
                        for v in range(ch * MOMENTUM_CHUNK,
                                       ti.min(nitems, (ch + 1) * MOMENTUM_CHUNK)):
                            q = listed_item(v, n1, qb0, qc0)
                            g2 += item_sweep_change(ct, bd, cs, q, nb, blocks)
                        cs.gpartial[gbase + ch] = g2
                        ch += threads
                    resident_barrier(threads)
                    grp = tid
                    while grp < MOMENTUM_GROUPS:
                        g2 = 0.0
                        for k in range(grp * per_group, ti.min(ngchunks, (grp + 1) * per_group)):
                            g2 += cs.gpartial[gbase + k]
                        cs.ggroup[sy * MOMENTUM_GROUPS + grp] = g2
                        grp += threads
                resident_barrier(threads)
                if tid == 0:
                    if check == 1:
                        res = partials_residual(cs, base, nchunks)
                        stop = 0
                        if res <= tol or sweeps >= max_sweeps:
                            stop = 1
                        cs.sys_residual[sy] = res
                        cs.sys_stop[sy] = stop
                    if ti.static(accel >= 1):
                        g2 = 0.0
                        for grp in range(MOMENTUM_GROUPS):
                            g2 += cs.ggroup[sy * MOMENTUM_GROUPS + grp]
                        cs.sys_beta[sy] = nncg_beta(g2, g2_prev, sweeps)
                        g2_prev = g2
                resident_barrier(threads)
                if check == 1:
                    residual = cs.sys_residual[sy]
                    done = cs.sys_stop[sy]
                if ti.static(accel == 1):
                    if done == 0:
                        beta = cs.sys_beta[sy]
                        for c in range(ncol):
                            s = cs.sys_start[c * nsys + sy] + tid
                            end = cs.sys_start[c * nsys + sy + 1]
                            while s < end:
                                item_momentum(p, ct, bd, cs.order[s], nb, beta, blocks, 1)
                                s += threads
                            resident_barrier(threads)
                if ti.static(accel == 2):
                    if done == 0:
                        # impulses and bodies apart (body_momentum), so in any order: no colours
                        beta = cs.sys_beta[sy]
                        v = tid
                        while v < nitems:
                            item_momentum(p, ct, bd, listed_item(v, n1, qb0, qc0), nb, beta,
                                          blocks, 0)
                            v += threads
                        i = q0 + tid
                        while i < q1:
                            body_momentum(p, cs, i, beta)
                            i += threads
                # every thread has read the decision before thread 0 may write the next one
                resident_barrier(threads)
        if tid == 0:
            st.sys_sweeps[sy] = sweeps
            st.sys_residual[sy] = residual
    ti.loop_config(serialize=True)
    for _ in range(1):
        gather_system_stats(p, st)


@ti.kernel
def quad_check_colours(p: ti.template(), wl: ti.template(), ct: ti.template(),
                       bd: ti.template(), cs: ti.template(), count: ti.i32,
                       blocks: ti.template()) -> float:
    """The coloured schedule's 'Quad ' check (measure "quad"): the `count` items as solve_item
    numbers them (bond blocks, or bonds, then contacts; a block holds the bonds where its
    particle is i), in fixed chunks of RESIDUAL_CHUNK items in parallel, then the partial sums
    in chunk order (deterministic, as sweep_residual); returns quad_residual of the sums."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range((count + RESIDUAL_CHUNK - 1) // RESIDUAL_CHUNK):
        nb = bd.total[None]
        if ti.static(blocks == 1):
            nb = p.count[None]
        n_part = p.count[None]
        sums = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        for q in range(c * RESIDUAL_CHUNK, ti.min(count, (c + 1) * RESIDUAL_CHUNK)):
            if q < nb:
                if ti.static(blocks == 1):
                    for m in range(particle_bond_count(bd, q)):
                        b = particle_bond(bd, q, m)
                        if bd.i[b] == q:
                            sums += check_item_bond(p, wl, bd, b)
                else:
                    sums += check_item_bond(p, wl, bd, q)
            else:
                sums += check_item_contact(p, wl, ct, q - nb, n_part)
        cs.qpartial[c] = sums
    ti.loop_config(serialize=True)
    for _ in range(1):
        sums = ti.Vector([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        for c in range((count + RESIDUAL_CHUNK - 1) // RESIDUAL_CHUNK):
            sums += cs.qpartial[c]
        cs.residual[None] = quad_residual(sums)
    return cs.residual[None]


# --- parallel colouring by rounds (GPU) ----------------------------------------------------------
# Round r gives colour r to a set of items that share no dynamic body: in each pass every
# waiting item whose bodies are all unclaimed in this round bids for them (atomic max of a
# key: the pass, then the item's body count, then a fixed hash of the item index), and an
# item that holds the best bid on every one of its bodies takes colour r and claims them.
# Max is order-independent, so the colours do not depend on thread timing. COLOUR_PASSES
# passes per round; the rounds go on until every active item has a colour. Bodies of an
# item: a contact's two particles (a wall is not a body), a bond's two particles, or a
# particle's bond block: the particle and all its intact bonded neighbours (as block_mask).
COLOUR_PASSES = 4
COLOURS_PER_LAUNCH = 4      # colours unrolled into one solve_colours call


@ti.func
def item_body_count(ct: ti.template(), bd: ti.template(), q, nb, blocks: ti.template()):
    count = 2
    if ti.static(blocks == 1):
        if q < nb:
            count = 1 + particle_bond_count(bd, q)
    return count


@ti.func
def item_body(ct: ti.template(), bd: ti.template(), q, nb, n, k, blocks: ti.template()):
    """The k-th body of item q, or -1 (a wall, a broken bond's end)."""
    b = -1
    is_block = 0
    if ti.static(blocks == 1):
        if q < nb:
            is_block = 1
            if k == 0:
                b = q
            else:
                e = particle_bond(bd, q, k - 1)
                if bd.state[e] == INTACT:
                    b = bd.i[e] + bd.j[e] - q
    if is_block == 0:
        if q < nb:
            b = bd.i[q] if k == 0 else bd.j[q]
        else:
            b = ct.i[q - nb] if k == 0 else ct.j[q - nb]
        if b >= n:
            b = -1
    return b


@ti.func
def colour_key(it, q, m):
    """Bid of item q with m bodies in pass `it`: the pass first, then the larger item (a
    particle block's thread solves all of the particle's bonds: the largest blocks take the
    first rounds, so that the later colours, each as slow as its slowest item on a GPU, hold
    small items only), then a fixed hash of q. Session 17, on the seed-1 shear: the same 21
    colours, and the sum over colours of each colour's largest item falls from 619 to 333
    bond-visits (28 colours, 910 to 398 for five samples batched)."""
    h = (ti.i64(q) * ti.i64(2654435761)) % ti.i64(4294967296)     # a bijection of q
    return (ti.i64(it) * ti.i64(1099511627776) + ti.i64(ti.min(m, 255)) * ti.i64(4294967296)
            + (ti.i64(4294967295) - h))


@ti.kernel
def colour_rounds_init(n: ti.i32, ct: ti.template(), bd: ti.template(), cs: ti.template(),
                       blocks: ti.template()):
    """Every item waiting (-2) or inactive (-1: broken bond, particle without intact bonds);
    bodies unclaimed; colour counts zero."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for b in range(n):
        cs.claim[b] = -1
        cs.best[b] = ti.i64(-1)
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range(MAX_COLOURS + 1):
        cs.start[c] = 0
    cs.coloured[None] = 0
    cs.active[None] = 0
    nb = bd.total[None]
    if ti.static(blocks == 1):
        nb = n
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for q in range(nb + ct.total[None]):
        active = 1
        if q < nb:
            if ti.static(blocks == 1):
                _, count = block_mask(bd, cs, q, 0)
                if count == 0:
                    active = 0
            elif bd.state[q] != INTACT:
                active = 0
        cs.item_colour[q] = -2 if active == 1 else -1
        cs.change[q] = ti.Vector([0.0, 0.0])
        if active == 1:
            cs.active[None] += 1


@ti.kernel
def colour_round(n: ti.i32, ct: ti.template(), bd: ti.template(), cs: ti.template(),
                 r: ti.i32, it: ti.i32, blocks: ti.template()):
    """The COLOUR_PASSES passes of round r (pass numbers it, it + 1, ...), each its bids then
    its takes, in one kernel call."""
    for t in ti.static(range(COLOUR_PASSES)):
        ti.loop_config(serialize=ti.static(backend.serial_loops()))
        for q in range(item_total(n, ct, bd, blocks)):
            colour_bid(n, ct, bd, cs, q, r, it + t, blocks)
        ti.loop_config(serialize=ti.static(backend.serial_loops()))
        for q in range(item_total(n, ct, bd, blocks)):
            colour_take(n, ct, bd, cs, q, r, it + t, blocks)


@ti.func
def bond_items(n, bd: ti.template(), blocks: ti.template()):
    """Items before the contacts: the bonds, or with blocks the n particle blocks."""
    nb = bd.total[None]
    if ti.static(blocks == 1):
        nb = n
    return nb


@ti.func
def item_total(n, ct: ti.template(), bd: ti.template(), blocks: ti.template()):
    return bond_items(n, bd, blocks) + ct.total[None]


@ti.func
def colour_bid(n, ct: ti.template(), bd: ti.template(), cs: ti.template(), q, r, it,
               blocks: ti.template()):
    nb = bond_items(n, bd, blocks)
    if cs.item_colour[q] == -2:
        free = 1
        m = item_body_count(ct, bd, q, nb, blocks)
        for k in range(m):
            b = item_body(ct, bd, q, nb, n, k, blocks)
            if b >= 0:          # nested: Taichi's `and` reads both sides (claim[-1] of a wall)
                if cs.claim[b] == r:
                    free = 0
        if free == 1:
            key = colour_key(it, q, m)
            for k in range(m):
                b = item_body(ct, bd, q, nb, n, k, blocks)
                if b >= 0:
                    ti.atomic_max(cs.best[b], key)


@ti.func
def colour_take(n, ct: ti.template(), bd: ti.template(), cs: ti.template(), q, r, it,
                blocks: ti.template()):
    nb = bond_items(n, bd, blocks)
    if cs.item_colour[q] == -2:
        m = item_body_count(ct, bd, q, nb, blocks)
        key = colour_key(it, q, m)
        win = 1
        for k in range(m):
            b = item_body(ct, bd, q, nb, n, k, blocks)
            if b >= 0:          # nested, as in colour_bid
                if cs.best[b] != key or cs.claim[b] == r:
                    win = 0
        if win == 1:
            cs.item_colour[q] = r
            for k in range(m):
                b = item_body(ct, bd, q, nb, n, k, blocks)
                if b >= 0:
                    cs.claim[b] = r
            cs.start[r + 1] += 1
            cs.coloured[None] += 1


@ti.kernel
def colour_rounds_order(n: ti.i32, p: ti.template(), ct: ti.template(), bd: ti.template(),
                        cs: ti.template(), st: ti.template(), ncol: ti.i32,
                        blocks: ti.template()):
    """CSR of the items by colour (cs.start) and, inside a colour, by system (cs.sys_start);
    within a colour's system in no fixed order: its items share no body, so the order changes
    no number. Sets st.colours."""
    ti.loop_config(serialize=True)
    for c in range(MAX_COLOURS):
        cs.start[c + 1] += cs.start[c]
    nsys = p.systems[None]
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for t in range(ncol * nsys):
        cs.sys_cursor[t] = 0
    nb = bd.total[None]
    if ti.static(blocks == 1):
        nb = n
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for q in range(nb + ct.total[None]):
        c = cs.item_colour[q]
        if c >= 0:
            ti.atomic_add(cs.sys_cursor[c * nsys + item_system(p, ct, bd, q, nb, blocks)], 1)
    ti.loop_config(serialize=True)
    for _ in range(1):
        acc = 0
        for t in range(ncol * nsys):
            cs.sys_start[t] = acc
            acc += cs.sys_cursor[t]
            cs.sys_cursor[t] = cs.sys_start[t]
        cs.sys_start[ncol * nsys] = acc
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for q in range(nb + ct.total[None]):
        c = cs.item_colour[q]
        if c >= 0:
            t = c * nsys + item_system(p, ct, bd, q, nb, blocks)
            cs.order[ti.atomic_add(cs.sys_cursor[t], 1)] = q
    st.colours[None] = ncol
    st.colour_overflow[None] = 0


@ti.kernel
def warm_start_colours(p: ti.template(), ct: ti.template(), bd: ti.template(), cs: ti.template(),
                       base: ti.i32, blocks: ti.template(), k: ti.template()):
    """The previous step's impulses of colours base .. base + k - 1 applied to their bodies,
    colour after colour (within a colour in parallel: its items share no body). A bond block
    applies the bonds whose first end is its particle, so each bond once."""
    for c in ti.static(range(k)):
        ti.loop_config(serialize=ti.static(backend.serial_loops()))
        for s in range(cs.start[ti.min(base + c, MAX_COLOURS)],
                       cs.start[ti.min(base + c + 1, MAX_COLOURS)]):
            warm_start_item(p, ct, bd, cs, s, blocks)


@ti.func
def warm_start_item(p: ti.template(), ct: ti.template(), bd: ti.template(), cs: ti.template(),
                    s, blocks: ti.template()):
    nb = bd.total[None]
    if ti.static(blocks == 1):
        nb = p.count[None]
    q = cs.order[s]
    if q < nb:
        if ti.static(blocks == 1):
            for e in range(bd.start[q], bd.start[q + 1]):
                if bd.state[e] == INTACT:
                    apply_bond_impulse(p, bd, e, bd.impulse[e])
        else:
            apply_bond_impulse(p, bd, q, bd.impulse[q])
    else:
        k = q - nb
        apply_impulse(p, ct.i[k], ct.j[k], ct.normal[k], ct.impulse[k])


# --- bonds: per-step frame and compliance, and post-solve update with yield -------------------
@ti.func
def bonds_prepare(p: ti.template(), bd: ti.template(), h: ti.template(), theta: ti.template(),
                  t_end: ti.template(), mode: ti.template(), k_m: ti.template(),
                  eta_m: ti.template(), k_k: ti.template(), eta_k: ti.template(),
                  tangent_factor: ti.template(), extrap: ti.template()):
    """Current frame and lever arms (the middle of the gap, bond_arms); tangential
    displacement and history carried into the new tangent plane (projected, length kept) and
    turned with the pair's spin about the bond's axis over the last step; extra compliance
    1/(theta H^2 K) and displacement terms; the warm start R_n + extrap (R_n - R_n-1)
    (extrap 0: the last step's impulse)."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for b in range(bd.total[None]):
        if bd.state[b] == INTACT:
            r_last = bd.impulse[b]
            if extrap > 0.0:
                bd.impulse[b] = r_last + extrap * (r_last - bd.impulse_prev[b])
            bd.impulse_prev[b] = r_last
            i, j = bd.i[b], bd.j[b]
            ri, rj = p.radius[i], p.radius[j]
            d = p.x[j] - p.x[i]
            dist = d.norm()
            n = d / dist
            bd.normal[b] = n
            if bd.turn_on[None] == 1:
                # the frame's turn (solve_bond_turn), from the warm start's normal impulse
                bd.turn[b] = ti.Vector([0.0, 0.0, 0.0])
                rn_warm = bd.impulse[b].dot(n)
                kappa = 0.0
                if rn_warm < 0.0:
                    kappa = -rn_warm * theta * h / dist
                bd.turn_k[b] = kappa
            hg = 0.5 * (dist - ri - rj)
            bd.half_gap[b] = hg
            ai, aj = ri + hg, rj + hg
            u = (p.v_old[j] + p.w_old[j].cross(-aj * n)) - (p.v_old[i] + p.w_old[i].cross(ai * n))
            un = u.dot(n)
            ut = u - un * n
            # the pair's turn about its axis over the last step (its mean spin, at the step's
            # start): the history turns with the bond (a rigid spin about the axis leaves its
            # force fixed to the grains, not to space)
            twist = h * 0.5 * (p.w_old[i] + p.w_old[j]).dot(n)
            bd.d_t[b] = turn_about(rotate_into_plane(bd.d_t[b], n), n, twist)
            bd.hd_t[b] = turn_about(rotate_into_plane(bd.hd_t[b], n), n, twist)
            bd.hk_t[b] = turn_about(rotate_into_plane(bd.hk_t[b], n), n, twist)
            dn_beg = (dist - ri - rj - bd.g0[b]) + (1.0 - theta) * h * un
            dt_beg = bd.d_t[b] + (1.0 - theta) * h * ut
            bd.d_t_beg[b] = dt_beg
            comp_n = 0.0
            off_n = 0.0
            off_t = ti.Vector([0.0, 0.0, 0.0])
            if mode == MODE_PAPER:
                comp_n = laws.creep_compliance_ti(t_end - bd.created[b], k_m, eta_m, k_k, eta_k)
            else:
                comp_n = 1.0 / k_m + h / eta_m + h / (eta_k + h * k_k)
                a = eta_k / (eta_k + h * k_k)
                off_n = bd.hd_n[b] + a * bd.hk_n[b]
                off_t = bd.hd_t[b] + a * bd.hk_t[b]
            comp_t = comp_n * tangent_factor
            bd.cn[b] = comp_n / (theta * h * h)
            bd.ct[b] = comp_t / (theta * h * h)
            bd.rhs_n[b] = (dn_beg - off_n) / (theta * h)
            bd.rhs_t[b] = (dt_beg - off_t) / (theta * h)


@ti.func
def turn_about(vec, n, angle):
    """vec (perpendicular to the unit n) turned by `angle` (rad) about n."""
    return ti.cos(angle) * vec + ti.sin(angle) * n.cross(vec)


@ti.func
def rotate_into_plane(vec, n):
    length = vec.norm()
    out = vec - vec.dot(n) * n
    ol = out.norm()
    res = ti.Vector([0.0, 0.0, 0.0])
    if ol > 0.0:
        res = out * (length / ol)
    return res


@ti.func
def bonds_finish(p: ti.template(), wl: ti.template(), bd: ti.template(), h: ti.template(),
                 theta: ti.template(), t_end: ti.template(), mode: ti.template(),
                 k_m: ti.template(), eta_m: ti.template(), k_k: ti.template(),
                 eta_k: ti.template(), tangent_factor: ti.template(), yield_stress: ti.template()):
    """Tangential displacement at the end of the step, Burgers history, brittle yield."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for b in range(bd.total[None]):
        if bd.state[b] == INTACT:
            i, j, n = bd.i[b], bd.j[b], bd.normal[b]
            u = bond_relative_velocity(p, wl, bd, b)
            ut = u - u.dot(n) * n
            bd.d_t[b] = bd.d_t_beg[b] + theta * h * ut
            r = bd.impulse[b]
            fn = -r.dot(n) / h                      # bond force, tension positive (N)
            ft = -(r - r.dot(n) * n) / h           # tangential bond force (N)
            if mode == MODE_BURGERS:
                a = 1.0 / (eta_k + h * k_k)
                bd.hd_n[b] += h * fn / eta_m
                bd.hk_n[b] = (eta_k * bd.hk_n[b] + h * fn) * a
                # tangential parameters are the normal ones divided by tangent_factor
                at = 1.0 / (eta_k / tangent_factor + h * k_k / tangent_factor)
                bd.hd_t[b] += h * ft / (eta_m / tangent_factor)
                bd.hk_t[b] = (eta_k / tangent_factor * bd.hk_t[b] + h * ft) * at
            sigma = fn / bd.area[b]
            tau = ft.norm() / bd.area[b]
            if sigma >= yield_stress or tau >= yield_stress:
                bd.state[b] = BROKEN_TENSION if sigma >= yield_stress else BROKEN_SHEAR
                ti.atomic_add(bd.broken[None], 1)
                bd.broken_time[b] = t_end
                ri = p.radius[i]
                gap = (p.x[j] - p.x[i]).norm() - ri - p.radius[j]
                bd.broken_pos[b] = p.x[i] + (ri + 0.5 * gap) * n


# --- integration and wall forces ---------------------------------------------------------------
@ti.func
def integrate(p: ti.template(), h: ti.template(), theta: ti.template()):
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(p.count[None]):
        p.x[i] += h * (theta * p.v[i] + (1.0 - theta) * p.v_old[i])


@ti.func
def project_overlaps(p: ti.template(), wl: ti.template(), ct: ti.template(), h: ti.template(),
                     slop: ti.template(), passes: ti.template()):
    """Position-only removal of interpenetration beyond `slop` (m) at the end of the step.

    The velocity-level Signorini condition never adds overlap in a converged step and never
    corrects existing overlap (that would inject kinetic energy). Steps that stop at the sweep
    cap (violent impacts) leave small overlaps that would otherwise accumulate, so after the
    integration the step's frictional contacts are swept `passes` times (serial, canonical
    order: deterministic) and each pair deeper than `slop` is moved apart along the line of
    centres, in inverse proportion to the masses (a wall or a fixed sphere does not move),
    down to `slop`. Velocities are untouched: no kinetic energy is created. Bonds are never
    projected (their overlap is their elastic state). Walls are taken at their end-of-step
    position."""
    n = p.count[None]
    nc = ct.total[None]
    ti.loop_config(serialize=True)
    for s in range(passes):
        for k in range(nc):
            project_contact(p, wl, ct, k, n, h, slop)


@ti.kernel
def project_overlaps_colours(p: ti.template(), wl: ti.template(), ct: ti.template(),
                             bd: ti.template(), cs: ti.template(), h: float, slop: float,
                             base: ti.i32, blocks: ti.template(), k: ti.template()):
    """project_overlaps for the contacts of colours base .. base + k - 1, colour after colour,
    each colour's at once (they share no body): the coloured schedule's projection."""
    for c in ti.static(range(k)):
        ti.loop_config(serialize=ti.static(backend.serial_loops()))
        for s in range(cs.start[ti.min(base + c, MAX_COLOURS)],
                       cs.start[ti.min(base + c + 1, MAX_COLOURS)]):
            nb = bd.total[None]
            if ti.static(blocks == 1):
                nb = p.count[None]
            q = cs.order[s]
            if q >= nb:
                project_contact(p, wl, ct, q - nb, p.count[None], h, slop)


@ti.func
def project_contact(p: ti.template(), wl: ti.template(), ct: ti.template(), k, n, h, slop):
    i, j = ct.i[k], ct.j[k]
    wi = p.inv_mass[i]
    if j < n:
        wj = p.inv_mass[j]
        d = p.x[j] - p.x[i]
        dist = d.norm()
        gap = dist - p.radius[i] - p.radius[j]
        if gap < -slop and dist > 0.0 and wi + wj > 0.0:
            nn = d / dist
            c = (-gap - slop) / (wi + wj)
            p.x[i] = p.x[i] - (c * wi) * nn
            p.x[j] = p.x[j] + (c * wj) * nn
    else:
        kw = j - n
        gap, nn, valid = contacts.wall_geometry(wl, kw, p.x[i] - h * wl.velocity[kw],
                                                p.radius[i])
        if valid == 1 and gap < -slop and wi > 0.0:
            p.x[i] = p.x[i] + (gap + slop) * nn


@ti.func
def wall_forces(p: ti.template(), wl: ti.template(), ct: ti.template(), h: ti.template()):
    """Force of the particles on each wall over the step: sum of contact impulses / H. Partial
    sums per (wall, chunk of WALL_CHUNK contacts) in parallel, then per wall over its chunks
    in chunk order (deterministic)."""
    nw = wl.count[None]
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for t in range(nw * ((ct.total[None] + WALL_CHUNK - 1) // WALL_CHUNK)):
        chunks = (ct.total[None] + WALL_CHUNK - 1) // WALL_CHUNK
        w, c = t // chunks, t % chunks
        s = ti.Vector([0.0, 0.0, 0.0])
        for k in range(c * WALL_CHUNK, ti.min(ct.total[None], (c + 1) * WALL_CHUNK)):
            if ct.j[k] == p.count[None] + w:
                s += ct.impulse[k]
        ct.wall_partial[t] = s
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for w in range(nw):
        chunks = (ct.total[None] + WALL_CHUNK - 1) // WALL_CHUNK
        s = ti.Vector([0.0, 0.0, 0.0])
        for c in range(chunks):
            s += ct.wall_partial[w * chunks + c]
        wl.force[w] = s / h


# --- the step's launches: the kernels between the host's decisions, fused ---------------------
# Each loop of these kernels is a loop of its own, in the order in which the ti.funcs above
# (predict, bonds_prepare, ..., wall_forces; kernels of their own until session 53) were
# launched one after the other: the same work and the same numbers, bit for bit, in two launches
# instead of eleven. A launch costs tens of microseconds of Taichi's Python, most of a small
# simulation's step (a bonded pair's step: 0.72 -> 0.48 ms), and each kernel compiles once per
# set of containers, with a fixed cost per instance (docs/performance.md).
@ti.kernel
def step_begin(p: ti.template(), wl: ti.template(), nb: ti.template(), bd: ti.template(),
               ct: ti.template(), alert: float, h: float, accel: float, gx: float, gy: float,
               gz: float, theta: float, t_end: float, mode: ti.i32, k_m: float, eta_m: float,
               k_k: float, eta_k: float, tangent_factor: float, extrap: float, mu: float,
               mu_break: float, bonds: ti.template(), factor: ti.i32, warm: ti.i32):
    """The step from the filling of its contact list to its warm start: contacts.contact_fill
    (ct.total and ct.start set by the count and scan before), predict, bonds_prepare and
    bonds_factor (`bonds`, static: the simulation holds bonds; `factor` 1: with bond blocks),
    contacts.contact_geometry and apply_warm_start (`warm` 1: the schedules that do not colour
    their items; the coloured ones warm-start colour by colour after colouring).
    `factor` and `warm` are run-time arguments (loop bounds times 0 or 1), not template ones:
    one compiled instance per set of containers serves every schedule and both bond
    relaxations (until session 68 each combination was an instance of its own, about a second
    of compiling on the CPU; the numbers are the same bit for bit). `bonds` stays a template
    argument: the bonds' code is most of the kernel, and a simulation without bonds (its own
    small bond buffer, so its own instance anyway) compiles it without them, faster."""
    contacts._contact_pass(p, wl, nb, bd, ct, alert, h, accel, True)
    predict(p, h, gx, gy, gz)
    if ti.static(bonds):
        bonds_prepare(p, bd, h, theta, t_end, mode, k_m, eta_m, k_k, eta_k, tangent_factor,
                      extrap)
        bonds_factor(p, bd, factor)
    contacts.contact_geometry(p, wl, bd, ct, h, theta, mu, mu_break, extrap)
    _apply_warm_start(p, ct, bd, warm)


@ti.kernel
def step_end(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
             h: float, theta: float, t_end: float, mode: ti.i32, k_m: float, eta_m: float,
             k_k: float, eta_k: float, tangent_factor: float, yield_stress: float, slop: float,
             passes: ti.i32, n: ti.i32, bonds: ti.template()):
    """The step after its sweeps: bonds_finish (`bonds`, static, as in step_begin),
    integrate, project_overlaps (`passes` passes, 0 for none: a run-time argument, one
    instance for every schedule), wall_forces and contacts.save_history (`n` particles). The
    coloured schedules project colour by colour after this kernel (they pass 0): its wall
    forces and contact history, which they used to follow, read no position and write
    nothing that the projection reads, so the order changes no number."""
    if ti.static(bonds):
        bonds_finish(p, wl, bd, h, theta, t_end, mode, k_m, eta_m, k_k, eta_k, tangent_factor,
                     yield_stress)
    integrate(p, h, theta)
    project_overlaps(p, wl, ct, h, slop, passes)
    wall_forces(p, wl, ct, h)
    contacts.save_history(ct, n)
