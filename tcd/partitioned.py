"""The serial Gauss-Seidel split over P CPU threads (schedule "partitioned").

The particles are split into P slabs of about equal work across one axis of the sample, cut
anew every step (a slab boundary is crossed by a layer of items about one grain thick, whatever
the particle numbering). The axis is the one along which the slabs alternate least in memory
(`interleaving`): a slab's thread writes its bodies and contacts during a sweep, and where two
slabs' records share a cache line the two threads stall each other (false sharing). An item
-- a contact, or a bond item (a particle's bond block, or a single bond) -- whose dynamic
bodies all lie in slab k is interior to k; the others are boundary items. One sweep is: the
P interior lists at once (unit k: slab k's bond items, then its contacts), then, on one
thread, the boundary list (bond items, then contacts); then the bonds' changes in P units at
once; then, on one thread, the convergence test and the conjugate-gradient (NNCG) momentum of
the boundary bonds and contacts; the momentum of the interior bonds and contacts opens the
next sweep's units. Every list is swept forward, or forward and backward in turn (the
`symmetric` sweep order), as in `solver.nlgs_serial`.
Two interior lists share no dynamic body, so running them at once gives exactly the numbers of
running them one after the other: the result depends on P (it fixes the visiting order), never
on thread timing or on how many threads Taichi really has. Same scenario, same P, same numbers.

The whole step is ONE kernel launch. Taichi's CPU thread pool wakes its threads for every
parallel loop (measured here: about 50 us, as long as a sweep of a few thousand contacts), so
the sweeps are not separate parallel loops: P worker iterations of one loop run all the sweeps
and meet at the end of each through counters in memory (sequentially consistent atomics, so
every body and impulse written before a counter's increment is seen by the thread that reads
it). Units are claimed, not assigned: a worker takes the next unit with an atomic increment,
waits until its sweep is released, runs it, and the worker that finishes a sweep's last unit
runs the boundary and releases the next sweep. A worker never waits for a unit that no running
thread holds, so the schedule finishes with any number of threads, one included.

Bonds are kept as in the serial kernel: each bond's change over a sweep is measured against a
snapshot of its impulse taken before the sweep. After the boundary list, the workers measure
the bonds' changes in P ranges of bond indices at once (a second phase of every sweep: those
only read impulses and write per-bond records), and the momentum and snapshot of a bond whose
two particles lie in slab k open worker k's next unit, as for the contacts; only the boundary
bonds' momentum stays on one thread.
"""

import taichi as ti

from . import solver as sk
from .solver import INTACT, SYSTEM_SPREAD
from .state import SLAB_BINS


# --- the item lists ------------------------------------------------------------------------------
@ti.func
def particle_work(ct: ti.template(), bd: ti.template(), q, blocks: ti.template()):
    """Relative cost of the items owned by particle q: its contacts (grouped under their first
    particle) and its bond items (a block solve costs about three contact updates per bond)."""
    w = ct.start[q + 1] - ct.start[q]
    if ti.static(blocks == 1):
        w += 3 * sk.particle_bond_count(bd, q)
    else:
        w += bd.start[q + 1] - bd.start[q]
    return w


@ti.func
def bond_item_list(bd: ti.template(), pt: ti.template(), q, parts,
                   blocks: ti.template()):
    """List of bond item q: its slab k when all its bodies lie in slab k, `parts` (the
    boundary) otherwise, -1 when inactive (a broken bond, a particle without intact bonds)."""
    lst = -1
    if ti.static(blocks == 1):
        k = pt.part[q]
        count = 0
        cross = 0
        for m in range(sk.particle_bond_count(bd, q)):
            b = sk.particle_bond(bd, q, m)
            if bd.state[b] == INTACT:
                count += 1
                if pt.part[bd.i[b] + bd.j[b] - q] != k:
                    cross = 1
        if count > 0:
            lst = k
            if cross == 1:
                lst = parts
    else:
        if bd.state[q] == INTACT:
            lst = pt.part[bd.i[q]]
            if pt.part[bd.j[q]] != lst:
                lst = parts
    return lst


@ti.func
def bond_list(bd: ti.template(), pt: ti.template(), b, parts):
    """Momentum list of bond b: slab k when both its particles lie in k, `parts` (the
    boundary) otherwise, -1 when broken."""
    lst = -1
    if bd.state[b] == INTACT:
        lst = pt.part[bd.i[b]]
        if pt.part[bd.j[b]] != lst:
            lst = parts
    return lst


@ti.func
def contact_list(p: ti.template(), ct: ti.template(), pt: ti.template(), c, parts):
    lst = pt.part[ct.i[c]]
    j = ct.j[c]
    if j < p.count[None]:
        if pt.part[j] != lst:
            lst = parts
    return lst


@ti.func
def slab_bin(p: ti.template(), q, axis, lo, span, bins):
    return ti.min(bins - 1, ti.max(0, ti.cast((p.x[q][axis] - lo) / span * bins, ti.i32)))


@ti.func
def cut_slabs(p: ti.template(), ct: ti.template(), bd: ti.template(), pt: ti.template(),
              axis, lo, span, parts, blocks: ti.template()):
    """pt.part: the particles' slabs for cuts across `axis` at the quantiles of a work
    histogram over SLAB_BINS bins (pt.hist: bin -> slab)."""
    n = p.count[None]
    bins = SLAB_BINS
    for c in range(bins):
        pt.hist[c] = 0
    total = 0
    for q in range(n):
        w = particle_work(ct, bd, q, blocks)
        pt.hist[slab_bin(p, q, axis, lo, span, bins)] += w
        total += w
    acc = 0
    for c in range(bins):
        k = 0
        if total > 0:
            k = ti.min(parts - 1, ti.cast(ti.cast(acc, ti.f64) * parts / total, ti.i32))
        acc += pt.hist[c]
        pt.hist[c] = k
    for q in range(n):
        pt.part[q] = pt.hist[slab_bin(p, q, axis, lo, span, bins)]


@ti.func
def interleaving(p: ti.template(), ct: ti.template(), pt: ti.template(), parts):
    """How often two slabs alternate along memory: consecutive particles in two slabs, and
    along the contacts (canonical order), consecutive interior contacts of two slabs
    (boundary items are swept while the other threads wait: they do not count; bonds and
    bond blocks are ordered by particle, so the particles' count stands for theirs). Each
    alternation is a cache line that two threads write during the same phase of a sweep
    (false sharing), and a Gauss-Seidel visit waits for every line it reads: on the
    2600-sphere pour (t = 0.48 s, 1000 sweeps, 2 threads; one thread: 0.23 s) slabs across y
    (805 particle alternations) took 0.218 s, across x (353) 0.18 s, across z (289) 0.151 s,
    whatever the boundary (244, 243 and 343 contacts)."""
    count = 0
    for q in range(1, p.count[None]):
        if pt.part[q] != pt.part[q - 1]:
            count += 1
    last = -1
    for c in range(ct.total[None]):
        lst = contact_list(p, ct, pt, c, parts)
        if lst < parts:
            if last >= 0 and lst != last:
                count += 1
            last = lst
    return count


@ti.kernel
def partition_items(p: ti.template(), ct: ti.template(), bd: ti.template(), pt: ti.template(),
                    parts: ti.i32, blocks: ti.template()):
    """Split the particles into `parts` slabs of about equal work across one axis (a work
    histogram over SLAB_BINS bins, cut at its quantiles) and list the items of each slab
    (bond items in `border`, CSR `bstart`; contacts in `corder`, CSR `cstart`; intact bonds,
    for their momentum, in `morder`, CSR `mstart`), list `parts` being the boundary.
    Canonical order inside every list. The axis is the one along which the slabs alternate
    least in memory (`interleaving`; the longest extent of the centres first on a tie): two
    threads writing one cache line stall each other, which costs far more than the few
    extra boundary items of another axis. Serial, O(items + SLAB_BINS) per axis,
    deterministic."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        n = p.count[None]
        nb = bd.total[None]
        if ti.static(blocks == 1):
            nb = n
        nc = ct.total[None]
        lo = p.x[0]
        hi = p.x[0]
        for q in range(n):
            lo = ti.min(lo, p.x[q])
            hi = ti.max(hi, p.x[q])
        longest = 0
        for a in ti.static(range(1, 3)):
            if hi[a] - lo[a] > hi[longest] - lo[longest]:
                longest = a
        axis = longest
        cut = -1                   # the axis pt.part was last cut across
        if parts > 1:
            best = -1
            for t in range(3):
                a = (longest + t) % 3
                if hi[a] - lo[a] > 0.0:
                    cut_slabs(p, ct, bd, pt, a, lo[a], hi[a] - lo[a], parts, blocks)
                    cut = a
                    cost = interleaving(p, ct, pt, parts)
                    if best < 0 or cost < best:
                        best = cost
                        axis = a
        if cut != axis:
            cut_slabs(p, ct, bd, pt, axis, lo[axis], ti.max(hi[axis] - lo[axis], 1e-12), parts,
                      blocks)
        for c in range(parts + 2):
            pt.bstart[c] = 0
            pt.cstart[c] = 0
            pt.mstart[c] = 0
        for q in range(nb):
            lst = bond_item_list(bd, pt, q, parts, blocks)
            if lst >= 0:
                pt.bstart[lst + 1] += 1
        for c in range(nc):
            pt.cstart[contact_list(p, ct, pt, c, parts) + 1] += 1
        for b in range(bd.total[None]):
            lst = bond_list(bd, pt, b, parts)
            if lst >= 0:
                pt.mstart[lst + 1] += 1
        for c in range(parts + 1):
            pt.bstart[c + 1] += pt.bstart[c]
            pt.cstart[c + 1] += pt.cstart[c]
            pt.mstart[c + 1] += pt.mstart[c]
        for c in range(parts + 1):
            pt.bcur[c] = pt.bstart[c]
            pt.ccur[c] = pt.cstart[c]
            pt.mcur[c] = pt.mstart[c]
        for q in range(nb):
            lst = bond_item_list(bd, pt, q, parts, blocks)
            if lst >= 0:
                pt.border[pt.bcur[lst]] = q
                pt.bcur[lst] += 1
        for c in range(nc):
            lst = contact_list(p, ct, pt, c, parts)
            pt.corder[pt.ccur[lst]] = c
            pt.ccur[lst] += 1
        for b in range(bd.total[None]):
            lst = bond_list(bd, pt, b, parts)
            if lst >= 0:
                pt.morder[pt.mcur[lst]] = b
                pt.mcur[lst] += 1


# --- one list of one sweep -----------------------------------------------------------------------
@ti.func
def sweep_list(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
               pt: ti.template(), lst, backward, measure, accel: ti.template(),
               blocks: ti.template()):
    """Bond items then contacts of list `lst`, forward or backward; the contacts' sums
    (|dR|, |R| when `measure`, |dR|^2 with NNCG) go to pt.sums[lst]."""
    n_part = p.count[None]
    a, b = pt.bstart[lst], pt.bstart[lst + 1]
    for s in range(a, b):
        q = pt.border[s]
        if backward == 1:
            q = pt.border[a + b - 1 - s]
        if ti.static(blocks == 1):
            sk.solve_particle_bonds(p, wl, bd, q, 0)
        else:
            sk.solve_bond_dr(p, wl, bd, q)
    dsum = 0.0
    rsum = 0.0
    g2 = 0.0
    a, b = pt.cstart[lst], pt.cstart[lst + 1]
    for s in range(a, b):
        k = pt.corder[s]
        if backward == 1:
            k = pt.corder[a + b - 1 - s]
        d2, da, ra = sk.visit_contact(p, wl, ct, k, n_part, measure, accel)
        if ti.static(accel == 1):
            g2 += d2
        if measure == 1:
            dsum += da
            rsum += ra
    pt.sums[lst] = ti.Vector([dsum, rsum, g2])


@ti.func
def open_unit(p: ti.template(), ct: ti.template(), bd: ti.template(), pt: ti.template(), k,
              accel: ti.template()):
    """Start of slab k's unit in sweep s > 0: the NNCG momentum of its interior bonds (then
    their snapshot) and contacts from sweep s - 1."""
    beta = pt.beta[None]
    for m in range(pt.mstart[k], pt.mstart[k + 1]):
        b = pt.morder[m]
        if ti.static(accel == 1):
            sk.bond_momentum(p, bd, b, beta, 1)
        bd.acc_d[b] = bd.impulse[b]
    if ti.static(accel == 1):
        for m in range(pt.cstart[k], pt.cstart[k + 1]):
            sk.contact_momentum(p, ct, pt.corder[m], beta, 1)


@ti.func
def bond_changes(bd: ti.template(), pt: ti.template(), k, parts):
    """Bookkeeping unit k: the changes over the sweep of the intact bonds in the k-th of
    `parts` ranges of bond indices, their sums into pt.bsums[k]."""
    nbd = bd.total[None]
    dsum = 0.0
    rsum = 0.0
    g2 = 0.0
    for b in range(k * nbd // parts, (k + 1) * nbd // parts):
        if bd.state[b] == INTACT:
            d2, da, ra = sk.bond_sweep_change(bd, b)
            g2 += d2
            dsum += da
            rsum += ra
    pt.bsums[k] = ti.Vector([dsum, rsum, g2])


@ti.func
def close_sweep(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
                st: ti.template(), pt: ti.template(), s, parts, max_sweeps, tol, check_every,
                accel: ti.template(), quad: ti.template()):
    """After the last bookkeeping unit of sweep s, on one thread: the convergence test (with
    `quad`, LMGC90's 'Quad ' check over all items on this thread: solver.quad_check_range);
    then either the end (pt.stop) or the momentum of the boundary bonds (then their snapshot)
    and contacts and the release of sweep s + 1."""
    sweeps = s + 1
    measure = 0
    if sweeps % check_every == 0 or sweeps >= max_sweeps:
        measure = 1
    dsum = 0.0
    rsum = 0.0
    g2 = 0.0
    for k in range(parts):
        dsum += pt.bsums[k][0]
        rsum += pt.bsums[k][1]
        g2 += pt.bsums[k][2]
    for k in range(parts + 1):
        dsum += pt.sums[k][0]
        rsum += pt.sums[k][1]
        g2 += pt.sums[k][2]
    done = 0
    if measure == 1:
        residual = 0.0
        if ti.static(quad == 1):
            residual = sk.quad_check_range(p, wl, ct, bd, 0, bd.total[None], 0, ct.total[None])
        else:
            residual = sk.impulse_residual(dsum, rsum)
        pt.residual[None] = residual
        if residual <= tol or sweeps >= max_sweeps:
            done = 1
    if done == 1:
        st.sweeps[None] = sweeps
        st.residual[None] = pt.residual[None]
        st.sys_sweeps[0] = sweeps
        st.sys_residual[0] = pt.residual[None]
        ti.atomic_add(pt.stop[None], 1)
    else:
        if ti.static(accel == 1):
            beta = sk.nncg_beta(g2, pt.g2_prev[None], sweeps)
            pt.beta[None] = beta
            pt.g2_prev[None] = g2
        open_unit(p, ct, bd, pt, parts, accel)
        ti.atomic_add(pt.released[None], 1)


@ti.kernel
def nlgs_partitioned(p: ti.template(), wl: ti.template(), ct: ti.template(), bd: ti.template(),
                     st: ti.template(), pt: ti.template(), parts: ti.i32, max_sweeps: ti.i32,
                     tol: float, check_every: ti.i32, symmetric: ti.i32,
                     accel: ti.template(), blocks: ti.template(), quad: ti.template()):
    """All sweeps of one step (see the module docstring); the items must have been listed by
    `partition_items` for the same `parts` and `blocks`. `symmetric`, `accel`, `blocks` and
    `quad` as in solver.nlgs_serial."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        pt.claim[None] = 0
        pt.finished[None] = 0
        pt.released[None] = 0
        pt.stop[None] = 0
        pt.beta[None] = 0.0
        pt.g2_prev[None] = 0.0
        pt.residual[None] = 0.0
        for b in range(bd.total[None]):
            bd.acc_d[b] = bd.impulse[b]
    # one worker per part, each spread over SYSTEM_SPREAD iterations (Taichi's CPU runtime
    # runs a loop of a few iterations on one thread: see solver.nlgs_serial); the one loop of
    # tcd that is always handed to the thread pool (backend.serial_loops)
    for t in range(parts * SYSTEM_SPREAD):
        if t % SYSTEM_SPREAD == 0:
            working = 1
            while working == 1:
                # unit u: phase u // parts (2 s: solving sweep s, 2 s + 1: its bookkeeping)
                u = ti.atomic_add(pt.claim[None], 1)
                ph = u // parts
                k = u % parts
                s = ph // 2
                # wait for the phase (atomic reads: never hoisted out of the loop)
                while ti.atomic_or(pt.released[None], 0) < ph and ti.atomic_or(pt.stop[None], 0) == 0:
                    pass
                if ti.atomic_or(pt.stop[None], 0) != 0:
                    working = 0
                elif ph % 2 == 0:
                    if s > 0:
                        open_unit(p, ct, bd, pt, k, accel)
                    measure = 0
                    if ti.static(quad == 0):
                        if (s + 1) % check_every == 0 or s + 1 >= max_sweeps:
                            measure = 1
                    sweep_list(p, wl, ct, bd, pt, k, (s % 2) * symmetric, measure, accel,
                              blocks)
                    if ti.atomic_add(pt.finished[None], 1) == ph * parts + parts - 1:
                        # the last solver of the sweep: the boundary list, then the bookkeeping
                        sweep_list(p, wl, ct, bd, pt, parts, (s % 2) * symmetric, measure, accel,
                              blocks)
                        ti.atomic_add(pt.released[None], 1)
                else:
                    bond_changes(bd, pt, k, parts)
                    if ti.atomic_add(pt.finished[None], 1) == ph * parts + parts - 1:
                        close_sweep(p, wl, ct, bd, st, pt, s, parts, max_sweeps, tol,
                                    check_every, accel, quad)
