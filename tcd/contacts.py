"""Broad phase (grid hashing) and contact building.

Broad phase: every particle is inserted into each grid cell its bounding box, enlarged by half
the alert distance, overlaps (count, serial scan, scatter). The grid is hashed: a cell's linear
index (z slowest) modulo a power-of-two table of buckets (about 4 per particle) picks its
bucket, and each entry keeps its cell's index, so a walk of a cell reads only the entries of
that cell. Memory and the per-step clear and scan follow the particle count, not the (tall,
mostly empty) pouring column; cells of one z slab map to consecutive buckets, so a dense bed
smaller than the table has no collisions at all. A large sphere thus spans several
small cells, which keeps the cost near-linear for the 8:1 size ratio of asphalt mixtures. A pair
(i, j), i < j, is examined only from the first cell common to both boxes, so it is found once.
Cells outside the grid are clamped to its border: still correct, only slower.
Batched systems (Simulation.batch) share the grid's geometry but not its cells: system s's cells
are numbered after those of systems 0..s-1 (a virtual grid per system), so two systems never
meet in the broad phase even when they occupy the same space, and a wall tagged with a system
only touches that system's particles.

Neighbour list (Verlet list): the grid is only walked to build, per particle, the list of
partners j > i whose gap is below the alert distance plus both particles' margins (half the
skin, more for fast grains), sorted ascending (two passes: count, scan, fill), with the
positions it was built at. Every step the contacts are picked from it; it is rebuilt when a
particle's motion since the build plus its reach over the step exceeds its margin, so it always
holds every pair that may touch by the end of the step, and the contacts are exactly those a
grid walk would find.
Contact building is two-pass per particle (count, scan, fill) over its list, which makes the
contact order canonical (i ascending, j ascending, walls last) and independent of thread
scheduling. Warm start: each contact looks up its pair in the previous
step's CSR list and starts from that impulse.
"""

import math

import taichi as ti

from . import backend
from .state import SCAN_MIN_CHUNK

PLANE, CYLINDER = 0, 1


@ti.func
def cell_of(g: ti.template(), p):
    c = ti.Vector([0, 0, 0])
    for a in ti.static(range(3)):
        k = ti.cast(ti.floor((p[a] - g.origin[None][a]) * g.inv_cell[None]), ti.i32)
        c[a] = ti.min(ti.max(k, 0), g.dims[None][a] - 1)
    return c


@ti.func
def cell_index(g: ti.template(), c):
    """Linear index of cell c in the (virtual) grid, z slowest."""
    return (c[2] * g.dims[None][1] + c[1]) * g.dims[None][0] + c[0]


@ti.func
def system_cells(g: ti.template(), p: ti.template(), i):
    """Offset of particle i's system in the virtual cell numbering (0 for system 0)."""
    return p.system[i] * (g.dims[None][0] * g.dims[None][1] * g.dims[None][2])


@ti.func
def touches(wl: ti.template(), p: ti.template(), k, i):
    """Wall k acts on particle i: untagged (-1) or tagged with i's system."""
    return wl.system[k] < 0 or wl.system[k] == p.system[i]


@ti.func
def bucket_of(g: ti.template(), linear):
    return linear & (g.buckets[None] - 1)


@ti.func
def reach(p: ti.template(), i, h, accel):
    """How far sphere i can travel over the coming step (m): contacts are built for every pair
    that may touch by the end of the step, not only for those already within the alert distance,
    so fast grains cannot pass through each other between two detections. `accel`: the
    gravity's magnitude (m/s^2; the 9.81 of every run before session 42, when it was a
    constant), to which grain i's external force over its mass is added."""
    return h * (p.v[i].norm() + (accel + p.f_ext[i].norm() * p.inv_mass[i]) * h)


@ti.func
def box_cells(g: ti.template(), p: ti.template(), nb: ti.template(), i, half_alert):
    """Cells of sphere i's bounding box enlarged by half the alert distance plus its margin
    in the neighbour list."""
    e = p.radius[i] + half_alert + nb.margin[i]
    return cell_of(g, p.x[i] - e), cell_of(g, p.x[i] + e)


@ti.func
def _grid_walk(p: ti.template(), g: ti.template(), nb: ti.template(), half_alert: ti.template(),
               scatter: ti.template()):
    """One walk of every particle's cells: per-bucket counts of the incidences (`scatter`
    False), or (True, after the counts' scan) each incidence written at its bucket's slots."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range(g.buckets[None]):
        g.cell_count[c] = 0
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(p.count[None]):
        lo, hi = box_cells(g, p, nb, i, half_alert)
        offset = system_cells(g, p, i)
        for cx in range(lo[0], hi[0] + 1):
            for cy in range(lo[1], hi[1] + 1):
                for cz in range(lo[2], hi[2] + 1):
                    c = cell_index(g, ti.Vector([cx, cy, cz])) + offset
                    b = bucket_of(g, c)
                    slot = ti.atomic_add(g.cell_count[b], 1)
                    if ti.static(scatter):
                        g.items[g.cell_start[b] + slot] = i
                        g.keys[g.cell_start[b] + slot] = c


@ti.kernel
def grid_walk(p: ti.template(), g: ti.template(), nb: ti.template(), half_alert: float):
    """The scattering walk (the counting one runs in _grid_count_scan, with its scan)."""
    _grid_walk(p, g, nb, half_alert, True)


@ti.kernel
def _grid_count_scan(p: ti.template(), g: ti.template(), nb: ti.template(), half_alert: float,
                     chunk: ti.i32) -> ti.i32:
    _grid_walk(p, g, nb, half_alert, False)
    _scan_loops(g.cell_count, g.cell_start, g.buckets[None], chunk, g.scan_partial)
    return g.cell_start[g.buckets[None]]


def grid_count(p, g, nb, half_alert: float) -> int:
    """The per-bucket counts of the particle-cell incidences and their scan (cell_start) in one
    launch; returns the number of incidences."""
    return _grid_count_scan(p, g, nb, half_alert, scan_chunk(g.nbuckets))


def grid_scatter(p, g, nb, half_alert: float) -> None:
    grid_walk(p, g, nb, half_alert)


_scan_scratch = {"field": None, "size": 0}


def scan_chunk(n: int) -> int:
    """Entries per thread of the parallel exclusive scan of n entries: about sqrt(n), at least
    SCAN_MIN_CHUNK, so that each thread's serial run and the one serial pass over the chunks
    are both about sqrt(n) long (a fixed 1024, sessions 15-37, gave a GPU six threads of 1024
    serial steps for the contacts' CSR of a 5857-sphere sample)."""
    return max(SCAN_MIN_CHUNK, math.isqrt(max(n, 0)) + 1)


@ti.func
def _scan_loops(count: ti.template(), start: ti.template(), n, chunk, partial: ti.template()):
    """start[k] = sum(count[:k]) for k <= n: chunk sums in parallel, their scan (serial, one
    entry per chunk), then each chunk's own scan in parallel (integers: exact, in any
    order). `partial`: at least n // chunk + 2 entries. Called at the top level of a kernel,
    after the loop that counts (its own launch until session 68: one more launch per contact
    list, and one more kernel instance to compile per container)."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range((n + chunk - 1) // chunk):
        s = 0
        for k in range(c * chunk, ti.min(n, (c + 1) * chunk)):
            s += count[k]
        partial[c] = s
    ti.loop_config(serialize=True)
    for _ in range(1):
        s = 0
        for c in range((n + chunk - 1) // chunk):
            t = partial[c]
            partial[c] = s
            s += t
        start[n] = s
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for c in range((n + chunk - 1) // chunk):
        s = partial[c]
        for k in range(c * chunk, ti.min(n, (c + 1) * chunk)):
            start[k] = s
            s += count[k]


@ti.kernel
def _exclusive_scan(count: ti.template(), start: ti.template(), n: ti.i32, chunk: ti.i32,
                    partial: ti.template()) -> ti.i32:
    """start[k] = sum(count[:k]) for k <= n (_scan_loops) alone."""
    _scan_loops(count, start, n, chunk, partial)
    return start[n]


def exclusive_scan(count, start, n: int) -> int:
    """start[k] = sum(count[:k]) for k <= n (in parallel, see _exclusive_scan); the total."""
    chunk = scan_chunk(n)
    need = n // chunk + 2
    if _scan_scratch["size"] < need:
        size = 64
        while size < need:
            size *= 2
        _scan_scratch["field"] = ti.field(ti.i32, shape=size)
        _scan_scratch["size"] = size
    return _exclusive_scan(count, start, n, chunk, _scan_scratch["field"])


@ti.func
def wall_geometry(wl: ti.template(), k, x, r):
    """Gap (m) between sphere (x, r) and wall k, normal from the sphere to the wall, and
    whether the sphere is within the wall's extent."""
    n = ti.Vector([0.0, 0.0, 0.0])
    gap = 1e30
    valid = 0
    d = wl.direction[k]
    rel = x - wl.point[k]
    if wl.kind[k] == PLANE:
        gap = rel.dot(d) - r
        n = -d
        valid = 1
    else:
        s = rel.dot(d)
        lo, hi = wl.lo[k], wl.hi[k]
        reach = r * (1.0 + wl.rim[k])         # rim: up to 2 r beyond an end (an alert margin)
        if s >= lo - reach and s <= hi + reach:
            perp = rel - s * d
            rho = perp.norm()
            if rho > 0.0:
                e = perp / rho
                if (s >= lo and s <= hi) or wl.rim[k] == 0:
                    # along the shell (or its extension by r beyond the ends: "extended")
                    n = e
                    gap = wl.radius[k] - rho - r
                    valid = 1
                else:
                    # beyond an end, the rim: the circle of the inner radius at that end;
                    # from the centre to its nearest point (closer than r only within r of
                    # the end; the range above also holds those an alert distance away)
                    edge = lo if s < lo else hi
                    c = (edge - s) * d + (wl.radius[k] - rho) * e
                    dist = c.norm()
                    if dist > 0.0:
                        n = c / dist
                        gap = dist - r
                        valid = 1
    return gap, n, valid


# a pair's bond state as bond_state reads it: solver.INTACT is 0 and its broken states are
# positive (tests/test_bonds.py checks that the two modules agree)
NO_BOND, BOND_INTACT = -1, 0


@ti.func
def bond_state(bd: ti.template(), i, j):
    """The state of the bond of pair (i, j), i < j, as stored with i: BOND_INTACT, a broken
    state (> 0), or NO_BOND when the pair was never bonded."""
    state = NO_BOND
    for k in range(bd.start[i], bd.start[i + 1]):
        if bd.j[k] == j:
            state = bd.state[k]
    return state


@ti.func
def pair_gap(p: ti.template(), i, j):
    return (p.x[j] - p.x[i]).norm() - p.radius[i] - p.radius[j]


# a list stays valid while every particle's motion plus reach is below this share of its margin
# (room for rounding in the triangle inequality the list's validity rests on)
MARGIN_USE = 1.0 - 1e-6


@ti.kernel
def neighbour_margins(p: ti.template(), nb: ti.template(), half_skin: float, h: float,
                      accel: float):
    """Each particle's margin for a new list: half the skin, or three times its reach over
    the coming step for a fast grain (a list that lasts it about two steps)."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(p.count[None]):
        nb.margin[i] = ti.max(half_skin, 3.0 * reach(p, i, h, accel))


@ti.func
def _neighbour_pass(p: ti.template(), g: ti.template(), nb: ti.template(),
                    half_alert: ti.template(), fill: ti.template()):
    """The neighbour list: every pair (i, j), j > i, with a gap below the alert distance plus
    both margins, found from the first cell their enlarged boxes share. One walk of the cells
    around each particle counts its neighbours (`fill` False, into nb.count) or writes them at
    nb.start (`fill` True) in ascending order, and keeps the positions the list was built at
    (nb.x_ref)."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(p.count[None]):
        lo, hi = box_cells(g, p, nb, i, half_alert)
        base = 0
        if ti.static(fill):
            base = nb.start[i]
        m = 0
        offset = system_cells(g, p, i)
        for cx in range(lo[0], hi[0] + 1):
            for cy in range(lo[1], hi[1] + 1):
                for cz in range(lo[2], hi[2] + 1):
                    c = ti.Vector([cx, cy, cz])
                    ci = cell_index(g, c) + offset
                    b = bucket_of(g, ci)
                    for s in range(g.cell_start[b], g.cell_start[b] + g.cell_count[b]):
                        j = g.items[s]
                        if j > i and g.keys[s] == ci:
                            lo_j, hi_j = box_cells(g, p, nb, j, half_alert)
                            first = ti.max(lo, lo_j)
                            if first[0] == c[0] and first[1] == c[1] and first[2] == c[2]:
                                if pair_gap(p, i, j) < 2.0 * half_alert + nb.margin[i] + nb.margin[j]:
                                    if ti.static(fill):
                                        nb.j[base + m] = j
                                    m += 1
        if ti.static(fill):
            # insertion sort: ascending partners whatever the cell order
            for a in range(1, m):
                key = nb.j[base + a]
                b = a - 1
                # nested tests: Taichi's `and` evaluates both sides (no short circuit by
                # default), which read nb.j[base - 1], before the field at base 0
                while b >= 0:
                    if nb.j[base + b] > key:
                        nb.j[base + b + 1] = nb.j[base + b]
                        b -= 1
                    else:
                        break
                nb.j[base + b + 1] = key
            nb.x_ref[i] = p.x[i]
        else:
            nb.count[i] = m


@ti.kernel
def neighbour_pass(p: ti.template(), g: ti.template(), nb: ti.template(), half_alert: float):
    """The filling pass (the counting one runs in neighbour_count, with its scan)."""
    _neighbour_pass(p, g, nb, half_alert, True)


@ti.kernel
def _neighbour_count_scan(p: ti.template(), g: ti.template(), nb: ti.template(),
                          half_alert: float, n: ti.i32, chunk: ti.i32) -> ti.i32:
    _neighbour_pass(p, g, nb, half_alert, False)
    _scan_loops(nb.count, nb.start, n, chunk, nb.scan_partial)
    return nb.start[n]


def neighbour_count(p, g, nb, half_alert: float, n: int) -> int:
    """Each particle's neighbours counted (nb.count) and scanned (nb.start) in one launch;
    returns the number of pairs."""
    return _neighbour_count_scan(p, g, nb, half_alert, n, scan_chunk(n))


@ti.kernel
def neighbour_list_stale(p: ti.template(), nb: ti.template(), h: float, accel: float) -> ti.i32:
    """1 when some particle's distance moved since the list was built plus its reach over
    the coming step exceeds its margin: a pair missing from the list could then touch. While
    none does, a pair outside the list (gap at the build >= alert + both margins) still has
    a gap of at least alert + both reaches, so it cannot be a contact candidate."""
    nb.stale[None] = 0
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(p.count[None]):
        if (p.x[i] - nb.x_ref[i]).norm() + reach(p, i, h, accel) > MARGIN_USE * nb.margin[i]:
            nb.stale[None] = 1
    return nb.stale[None]


@ti.func
def _contact_pass(p: ti.template(), wl: ti.template(), nb: ti.template(), bd: ti.template(),
                  ct: ti.template(), alert: ti.template(), h: ti.template(), accel: ti.template(),
                  fill: ti.template()):
    """Each particle's contact candidates from its neighbour list: partners j whose gap is
    below the alert distance plus both reaches (may touch by the end of the step) and not
    held by an intact bond, then the walls within reach. Counts them (`fill` False, into
    ct.count) or writes them at ct.start (`fill` True) in canonical order: particle partners
    ascending (the list's order), then walls."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(p.count[None]):
        base = 0
        if ti.static(fill):
            base = ct.start[i]
        m = 0
        reach_i = reach(p, i, h, accel)
        for s in range(nb.start[i], nb.start[i + 1]):
            j = nb.j[s]
            if pair_gap(p, i, j) < alert + reach_i + reach(p, j, h, accel):
                if bond_state(bd, i, j) != BOND_INTACT:
                    if ti.static(fill):
                        ct.j[base + m] = j
                    m += 1
        for k in range(wl.count[None]):
            gap, n, valid = wall_geometry(wl, k, p.x[i], p.radius[i])
            if valid == 1 and touches(wl, p, k, i) and gap < alert + reach_i + h * wl.velocity[k].norm():
                if ti.static(fill):
                    ct.j[base + m] = p.count[None] + k
                m += 1
        if ti.static(fill):
            for a in range(m):
                ct.i[base + a] = i
        else:
            ct.count[i] = m


@ti.kernel
def contact_pass(p: ti.template(), wl: ti.template(), nb: ti.template(), bd: ti.template(),
                 ct: ti.template(), alert: float, h: float, accel: float):
    """The filling pass alone (the counting one runs in contact_count, with its scan; a step
    fills in solver.step_begin)."""
    _contact_pass(p, wl, nb, bd, ct, alert, h, accel, True)


@ti.kernel
def _contact_count_scan(p: ti.template(), wl: ti.template(), nb: ti.template(),
                        bd: ti.template(), ct: ti.template(), alert: float, h: float,
                        accel: float, n: ti.i32, chunk: ti.i32) -> ti.i32:
    _contact_pass(p, wl, nb, bd, ct, alert, h, accel, False)
    _scan_loops(ct.count, ct.start, n, chunk, ct.scan_partial)
    return ct.start[n]


def contact_count(p, wl, nb, bd, ct, alert: float, h: float, accel: float, n: int) -> int:
    """Each particle's contact candidates counted (ct.count) and scanned (ct.start) in one
    launch; returns the number of contacts."""
    return _contact_count_scan(p, wl, nb, bd, ct, alert, h, accel, n, scan_chunk(n))


def contact_fill(p, wl, nb, bd, ct, alert: float, h: float, accel: float) -> None:
    contact_pass(p, wl, nb, bd, ct, alert, h, accel)


@ti.func
def contact_geometry(p: ti.template(), wl: ti.template(), bd: ti.template(), ct: ti.template(),
                     h: ti.template(), theta: ti.template(), mu: ti.template(),
                     mu_break: ti.template(), extrap: ti.template()):
    """Frame, gap at the predicted configuration, Delassus diagonal, friction (`mu` between
    particles, `mu_break` between two whose bond broke, each wall's own), warm start:
    the contact's impulse of the last step R_n, or with `extrap` = c > 0, where the contact also
    carried an impulse the step before, R_n + c (R_n - R_n-1) (then the cone's normal half:
    a negative normal impulse starts from zero; the first visit projects the rest)."""
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for k in range(ct.total[None]):
        i, j = ct.i[k], ct.j[k]
        ri = p.radius[i]
        n = ti.Vector([0.0, 0.0, 1.0])
        gap = 0.0
        rj = 0.0
        vj = ti.Vector([0.0, 0.0, 0.0])
        wj = ti.Vector([0.0, 0.0, 0.0])
        im_j = 0.0
        ii_j = 0.0
        f = mu
        if j < p.count[None]:
            d = p.x[j] - p.x[i]
            dist = d.norm()
            if dist > 0.0:
                n = d / dist
            rj = p.radius[j]
            gap = dist - ri - rj
            vj, wj = p.v_old[j], p.w_old[j]
            im_j, ii_j = p.inv_mass[j], p.inv_inertia[j]
            if mu_break != mu:
                if bond_state(bd, i, j) > BOND_INTACT:
                    f = mu_break
        else:
            kw = j - p.count[None]
            gap, n, valid = wall_geometry(wl, kw, p.x[i], ri)
            vj = wl.velocity[kw]
            f = wl.friction[kw]
        u = (vj + wj.cross(-rj * n)) - (p.v_old[i] + p.w_old[i].cross(ri * n))
        g_beg = gap + (1.0 - theta) * h * u.dot(n)
        ct.normal[k] = n
        ct.gap[k] = g_beg
        # existing overlap is not corrected (no energy injected): target end gap max(g_beg, 0)
        ct.rhs[k] = ti.max(g_beg, 0.0) / (theta * h)
        ct.wnn[k] = p.inv_mass[i] + im_j
        ct.wtt[k] = p.inv_mass[i] + im_j + ri * ri * p.inv_inertia[i] + rj * rj * ii_j
        ct.mu[k] = f
        r = ti.Vector([0.0, 0.0, 0.0])
        r_old = ti.Vector([0.0, 0.0, 0.0])
        for q in range(ct.prev_start[i], ct.prev_start[i + 1]):
            if ct.prev_j[q] == j:
                r = ct.prev_impulse[q]
                r_old = ct.prev_old[q]
        ct.impulse_old[k] = r
        if extrap > 0.0 and r_old.dot(r_old) > 0.0:
            r = r + extrap * (r - r_old)
        rn = r.dot(n)
        if rn < 0.0:
            r = ti.Vector([0.0, 0.0, 0.0])
        ct.impulse[k] = r


@ti.func
def save_history(ct: ti.template(), n: ti.template()):
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for k in range(ct.total[None]):
        ct.prev_j[k] = ct.j[k]
        ct.prev_impulse[k] = ct.impulse[k]
        ct.prev_old[k] = ct.impulse_old[k]
    ti.loop_config(serialize=ti.static(backend.serial_loops()))
    for i in range(n + 1):
        ct.prev_start[i] = ct.start[i]
    ct.prev_total[None] = ct.total[None]
