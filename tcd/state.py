"""Field containers: particles, walls, the broad-phase grid, contacts and bonds.

Taichi fields grouped in small data-oriented classes (the solver's per-item records laid out
array-of-structs on the CPU, struct-of-arrays on the GPU: aos_layout), passed to kernels as
template arguments. Sizes that change between runs (particle count, grid shape, totals) are
runtime scalars inside the containers, and capacities come in power-of-two classes: containers
are recycled through a pool (`acquire` / `release`), so a new simulation of a similar size reuses
fields and compiled kernels instead of compiling again (seconds per kernel set). A container
that overflows is replaced by one of a larger class; nothing is silently truncated.
All real fields use the precision chosen by `tcd.init`.
"""
from __future__ import annotations

import itertools
import os

import numpy as np
import taichi as ti

from . import backend
from .copies import _column_offsets, _rows_in, _rows_out

MAX_WALLS = 64
MAX_SYSTEMS = 64            # independent systems (samples) batched in one simulation
MAX_PARTS = 64              # threads of the partitioned Gauss-Seidel (tcd/partitioned.py)
# sweeps per step: the partitioned Gauss-Seidel claims about 2 MAX_PARTS units per sweep from an
# i32 counter (1.3e9 at this bound); config.py's max_sweeps bounds are the same number
MAX_SWEEPS = 10**7
SLAB_BINS = 4096            # its work histogram across the sample, cut into slabs
COLOUR_WORDS = 8            # 32-bit words of the per-body colour mask
MAX_COLOURS = 32 * COLOUR_WORDS
RESIDUAL_CHUNK = 256       # items per partial sum of the coloured schedule's residual
# the resident schedule's NNCG sum |dR|^2: items per partial sum, and the groups of partials
# summed before the last sum (every thread of a GPU block busy: 256-item chunks left 37 of a
# block's 256 threads working on the seed-1 shear's 9300 items)
MOMENTUM_CHUNK = 32
MOMENTUM_GROUPS = 32
WALL_CHUNK = 4096          # contacts per partial sum of the wall forces


def field_record(cls):
    """Mark a container class as data-oriented for Taichi, as `ti.data_oriented` does, without
    the attribute hook that decorator installs. A data-oriented object passed as a
    `ti.template()` argument is keyed by a weak reference to it, and may be assigned to a name
    inside a kernel; Taichi tests both with `hasattr(obj, "_data_oriented")`, and this class
    attribute answers them. `ti.data_oriented` also replaces `__getattribute__` with a Python
    function so that kernels defined as methods bind to the object; tcd's containers have no
    kernel methods, and that hook made every attribute read of a container (each launch's
    argument checks, every `ct.total` in the step loop) a Python call: about 400 per time step
    (a step of a bonded pair of spheres took 5.2 ms with the hook, 3.9 ms without)."""
    cls._data_oriented = True
    return cls


# Smallest capacity class. Taichi compiles each kernel once per set of containers it is
# given, and compiling is most of the cost of a small simulation (about 3 s for the serial
# sweep's kernel alone, on this project's machine). With a floor of 1024 slots every
# simulation of up to about 250 spheres draws the same classes from the pool, so a process
# that runs many small ones in turn (a test suite, a parameter study) reuses their kernels:
# four test files in one process built 2120 kernel instances with a floor of 64 and 1041
# with 1024 (docs/measurements.md, session 24). A simulation of six spheres holds 0.66 MB of
# fields instead of 68 kB; from 1024 spheres up nothing changes. The buffer of a
# simulation without bonds keeps its 64 slots (one class for every size already).
MIN_SLOTS = 1024


def capacity_class(n: int, minimum: int | None = None) -> int:
    """Smallest size >= max(n, minimum) of the form 2^k x (1, 1.25, 1.5 or 1.75): classes close
    enough that a container wastes at most a quarter of its slots, few enough that the pool
    (and the kernels compiled for it) is reused by simulations of similar sizes. `minimum`:
    MIN_SLOTS unless given."""
    minimum = MIN_SLOTS if minimum is None else minimum
    c = minimum
    while c < n:
        c *= 2
    for q in (5, 6, 7):
        if c > minimum and c // 8 * q >= n:
            return c // 8 * q
    return c


def _vec(n):
    return ti.Vector.field(3, backend.real(), shape=n)


def _real(n):
    return ti.field(backend.real(), shape=n)


def _int(n, dtype=ti.i32):
    return ti.field(dtype, shape=n)


SCAN_MIN_CHUNK = 64             # counts per thread of the parallel exclusive scan, at least


def _scan_scratch(n):
    """The chunk sums of the container's scans of up to n counts (contacts._scan_loops, at
    least SCAN_MIN_CHUNK counts per chunk: n // SCAN_MIN_CHUNK + 2 entries)."""
    return ti.field(ti.i32, shape=n // SCAN_MIN_CHUNK + 2)


def _scalar(dtype=ti.i32):
    return ti.field(dtype, shape=())


def aos_layout() -> bool:
    """Whether the solver's records are laid out AoS (`_struct`): by default on the CPU (one
    cache line serves a body's or a contact's record), SoA on the GPU (threads of a warp read
    neighbouring addresses, and Taichi 1.7.4's CUDA code faults on f64 vectors inside an AoS
    record: CUDA_ERROR_MISALIGNED_ADDRESS). The environment variable TCD_LAYOUT=aos|soa
    overrides the default. No number depends on the layout."""
    layout = os.environ.get("TCD_LAYOUT", "")
    if layout not in ("", "aos", "soa"):
        raise ValueError(f"TCD_LAYOUT={layout!r}: expected 'aos' or 'soa'")
    if layout:
        return layout == "aos"
    return backend.arch() == "cpu"


def _struct(n, *fields):
    """Place `fields` (created without shape) side by side, one record per row (AoS): the
    solver reads all of them for a body or a contact at once, so one cache line serves them.
    SoA (each field its own array) where `aos_layout()` says so. No number depends on it."""
    if aos_layout():
        ti.root.dense(ti.i, n).place(*fields)
    else:
        for f in fields:
            ti.root.dense(ti.i, n).place(f)
    return fields


def _vec_row():
    return ti.Vector.field(3, backend.real())


def _real_row():
    return ti.field(backend.real())


_pool: dict = {}
_serials = itertools.count()


def acquire(cls, capacity: int, *args, minimum: int | None = None):
    """A container of `cls` with at least `capacity` slots, recycled when one is free (its
    capacity class from `minimum` slots, MIN_SLOTS unless given): the oldest free one of its
    class. Taichi compiles a kernel once per set of containers it is given; handing out the
    oldest keeps the sets together (after two simulations held at once, the next gets the
    first one's set, whatever order they were freed in, where the last one freed of each kind
    mixed the two sets into new ones to compile for): the suite compiled 1958 kernel instances
    instead of 2372, 399 s instead of 465 s with an empty kernel cache (session 68)."""
    cap = capacity_class(capacity, minimum)
    free = _pool.setdefault((cls, cap) + args, [])
    if free:
        obj = free.pop(min(range(len(free)), key=lambda k: free[k]._pool_serial))
    else:
        obj = cls(cap, *args)
        obj._pool_serial = next(_serials)
    obj.reset()
    return obj


def release(obj) -> None:
    if obj is not None:
        _pool.setdefault((type(obj), obj.capacity) + obj.pool_args, []).append(obj)


def get(field, n):
    """First n rows of a field as NumPy."""
    return field.to_numpy()[:n]


def put(field, values) -> None:
    """Write `values` into the first rows of a field (the rest is zeroed)."""
    values = np.asarray(values)
    shape = field.shape + ((field.n,) if isinstance(field, ti.MatrixField) else ())
    full = np.zeros(shape, _np_dtype(field))
    full[: len(values)] = values
    field.from_numpy(full)


def _same_rows(fields) -> int:
    rows = {f.shape for f in fields}
    if len(rows) != 1 or len(next(iter(rows))) != 1:
        raise ValueError(f"fields of one row copy must share one 1-D shape, not {sorted(rows)}")
    return next(iter(rows))[0]


def get_rows(fields, n) -> list:
    """`[get(f, n) for f in fields]` in one kernel launch: fields of one 1-D shape (scalars or
    vectors of f64, f32 or 32-bit integers, all exact in the f64 copy). Taichi compiles its
    `to_numpy` once per field, about 0.1 s each on the CPU; this compiles once per tuple of
    fields (a container's record) instead (tests/test_bonds.py with an empty kernel cache:
    804 kernel instances before, 567 with the particles' and bonds' copies grouped). The copy
    is an f64 array of n rows and one column per scalar component."""
    fields = tuple(fields)
    _same_rows(fields)
    offsets = _column_offsets(fields)
    out = np.zeros((max(n, 1), offsets[-1]), np.float64)
    if n > 0:
        _rows_out(fields, out, n)
    arrays = []
    for f, off in zip(fields, offsets):
        if isinstance(f, ti.MatrixField):
            arrays.append(out[:n, off:off + f.n].astype(_np_dtype(f)))
        else:
            arrays.append(out[:n, off].astype(_np_dtype(f)))
    return arrays


def put_rows(fields, values) -> None:
    """`for f, v in zip(fields, values): put(f, v)` in one kernel launch (see get_rows): every
    value has the same number of rows m; the fields' rows from m on are zeroed."""
    fields = tuple(fields)
    rows = _same_rows(fields)
    values = [np.asarray(v) for v in values]
    m = {len(v) for v in values}
    if len(m) != 1:
        raise ValueError(f"values of one row copy must have one row count, not {sorted(m)}")
    m = m.pop()
    if m > rows:
        raise ValueError(f"{m} rows do not fit fields of {rows}")
    offsets = _column_offsets(fields)
    arr = np.zeros((max(m, 1), offsets[-1]), np.float64)
    for f, off, v in zip(fields, offsets, values):
        width = f.n if isinstance(f, ti.MatrixField) else 1
        arr[:m, off:off + width] = v.reshape(m, width)
    _rows_in(fields, arr, m, rows)


def get_fields(container, keys, n) -> dict:
    """{key: get(getattr(container, key), n)} for each of `keys`, through get_rows."""
    return dict(zip(keys, get_rows([getattr(container, key) for key in keys], n)))


def put_fields(container, values: dict) -> None:
    """put(getattr(container, key), value) for each item of `values`, through put_rows."""
    put_rows([getattr(container, key) for key in values], list(values.values()))


def _np_dtype(field):
    dt = field.dtype
    if dt == ti.f64:
        return np.float64
    if dt == ti.f32:
        return np.float32
    if dt == ti.u32:
        return np.uint32
    return np.int32


@field_record
class Particles:
    """Rigid spheres; count: how many of the `capacity` slots are used. Model: radius (m),
    inv_mass (1/kg), inv_inertia (1/(kg m^2)), layer (0 bottom course, 1 top course), external
    force f_ext (N). State: x (m), v (m/s), w (rad/s); v_old, w_old hold the velocities at the
    beginning of the step. (v, w, radius, inv_mass, inv_inertia) are one record per body (AoS):
    the Gauss-Seidel hot loop reads them together."""
    pool_args = ()

    def __init__(self, capacity: int):
        c = self.capacity = capacity
        # the solver's per-body record: velocities and the model data it multiplies them by
        self.v, self.w, self.radius, self.inv_mass, self.inv_inertia = _struct(
            c, _vec_row(), _vec_row(), _real_row(), _real_row(), _real_row())
        self.x = _vec(c)
        self.v_old, self.w_old, self.f_ext = _vec(c), _vec(c), _vec(c)
        self.layer = _int(c)
        # batched systems: particle i belongs to system[i]; system s holds the contiguous
        # particles sys_start[s] .. sys_start[s + 1] - 1 (one system: all of them)
        self.system = _int(c)
        self.sys_start = _int(MAX_SYSTEMS + 1)
        self.systems = _scalar()
        self.count = _scalar()

    def reset(self):
        self.count[None] = 0
        self.systems[None] = 1


@field_record
class WallFields:
    """Device copy of the walls: kind (0 plane, 1 cylinder), point, direction, radius, axial
    range lo/hi, friction, velocity over the current step (m/s) and force from the particles
    over the last step (N); system: the batched system whose particles it touches (-1: all);
    rim: a cylinder's ends (walls.Wall.edges: 1 "rim", 0 "extended")."""
    pool_args = ()

    def __init__(self, capacity: int = MAX_WALLS):
        m = self.capacity = capacity
        self.kind = _int(m)
        self.point, self.direction, self.velocity, self.force = _vec(m), _vec(m), _vec(m), _vec(m)
        self.radius, self.lo, self.hi, self.friction = _real(m), _real(m), _real(m), _real(m)
        self.system = _int(m)
        self.rim = _int(m)              # a cylinder's ends: 1 its rim only, 0 extended
        self.count = _scalar()

    def reset(self):
        self.count[None] = 0
        self.force.fill(0)


@field_record
class Grid:
    """Hashed uniform grid for the broad phase (counting sort of particles by the cells their
    enlarged bounding box overlaps). Runtime shape: origin (m), inv_cell (1/m), dims of the
    virtual grid, buckets (a power of two <= `cell_capacity`): cell c goes to bucket
    c mod buckets. Per bucket: cell_count, cell_start (CSR); per particle-cell incidence
    (`capacity`): items (particle) and keys (cell)."""
    def __init__(self, capacity: int, cell_capacity: int | None = None):
        self.capacity = capacity
        cc = self.cell_capacity = cell_capacity or capacity
        self.pool_args = (cc,)
        self.cell_count, self.cell_start = _int(cc), _int(cc + 1)
        self.scan_partial = _scan_scratch(cc)
        self.items, self.keys = _int(capacity), _int(capacity)
        self.origin = ti.Vector.field(3, backend.real(), shape=())
        self.dims = ti.Vector.field(3, ti.i32, shape=())
        self.inv_cell = _scalar(backend.real())
        self.buckets = _scalar()

    def reset(self):
        self.buckets[None] = self.nbuckets = 0

    def configure(self, origin, cell: float, dims, buckets: int) -> None:
        ncells = int(np.prod(dims))
        if ncells >= 2**31:
            raise ValueError("grid has too many cells for 32-bit cell indices")
        if buckets > self.cell_capacity or buckets & (buckets - 1):
            raise ValueError(f"bucket count {buckets} is not a power of two <= {self.cell_capacity}")
        self.origin[None] = [float(o) for o in origin]
        self.dims[None] = [int(d) for d in dims]
        self.inv_cell[None] = 1.0 / float(cell)
        self.buckets[None] = self.nbuckets = int(buckets)


@field_record
class Neighbours:
    """Neighbour (Verlet) list of the broad phase: per particle i (CSR: count, start over
    `particle_capacity`), the partners j > i within the alert distance plus both margins when
    it was built, ascending, in j (`capacity` pairs); x_ref: the positions it was built at;
    margin: each particle's margin (m); stale: scratch of contacts.neighbour_list_stale."""

    def __init__(self, capacity: int, particle_capacity: int):
        self.capacity, self.pool_args = capacity, (particle_capacity,)
        self.j = _int(capacity)
        self.count, self.start = _int(particle_capacity), _int(particle_capacity + 1)
        self.scan_partial = _scan_scratch(particle_capacity)
        self.x_ref = _vec(particle_capacity)
        self.margin = _real(particle_capacity)
        self.stale = _scalar()
        self.total = _scalar()

    def reset(self):
        self.total[None] = 0


@field_record
class Contacts:
    """Frictional contacts of one step, in canonical order: grouped by first particle i
    (ascending), then partner j ascending (particles, then walls as j = N + wall index).

    Per contact: i, j, normal n (i to j), gap g_beg at the predicted configuration (m),
    rhs = max(g_beg, 0) / (theta H) (m/s), wnn, wtt (Delassus diagonal, 1/kg), mu, impulse R
    (N s, global vector), colour. Per particle: count and start (CSR, `particle_capacity`).
    The previous step's (j, R, start) are kept in prev_* for warm starting, with prev_old:
    each of those contacts' impulse the step before (impulse_old: the current contacts'
    previous-step impulse; the extrapolated warm start reads both). The solver's
    fields (i, j, normal, impulse, rhs, wnn, wtt, mu) are one record per contact (AoS)."""

    def __init__(self, capacity: int, particle_capacity: int):
        self.capacity, self.pool_args = capacity, (particle_capacity,)
        c, n = capacity, particle_capacity
        # the solver's per-contact record (AoS), read whole at every local solve
        (self.i, self.j, self.normal, self.impulse, self.rhs, self.wnn, self.wtt,
         self.mu) = _struct(c, ti.field(ti.i32), ti.field(ti.i32), _vec_row(), _vec_row(),
                            _real_row(), _real_row(), _real_row(), _real_row())
        self.colour = _int(c)
        self.gap = _real(c)
        # accelerated (NNCG) Gauss-Seidel: search direction and last sweep's change per contact
        self.acc_p, self.acc_d = _vec(c), _vec(c)
        self.count, self.start = _int(n), _int(n + 1)
        self.scan_partial = _scan_scratch(n)
        self.prev_j, self.prev_impulse, self.prev_start = _int(c), _vec(c), _int(n + 1)
        self.impulse_old, self.prev_old = _vec(c), _vec(c)
        self.total = _scalar()
        self.prev_total = _scalar()
        # wall forces: partial sums per (wall, chunk of WALL_CHUNK contacts)
        self.wall_partial = ti.Vector.field(3, backend.real(),
                                            shape=MAX_WALLS * (capacity // WALL_CHUNK + 1))

    def reset(self):
        # a recycled buffer holds its last simulation's lists: empty ranges for every particle
        # (a simulation that never stepped gives them in its state, which a batch merges)
        self.total[None] = 0
        self.prev_total[None] = 0
        self.prev_start.fill(0)
        self.start.fill(0)


@field_record
class Bonds:
    """Bonded (Burgers) contacts: a fixed set sorted by (i, j), i < j, CSR start per particle.

    Model: i, j, g0 (gap at creation, m), created (time, s), area (pi min(r)^2, m^2).
    State: state (0 intact, 1 broken in tension, 2 broken in shear), impulse R (N s),
    impulse_prev (R of the step before: the extrapolated warm start),
    d_t (tangential displacement, m, global vector in the tangent plane),
    Burgers history (normal: hd_n dashpot, hk_n Kelvin; tangential: hd_t, hk_t, m),
    broken_time (s, NaN while intact), broken_pos (m).
    Per step: normal, half_gap (half the gap at the step's start: the bond acts at the middle
    of the gap, r_i + half_gap from i's centre and r_j + half_gap from j's, solver.bond_arms),
    rhs_n, rhs_t (displacement terms / (theta H)), cn, ct (extra compliance
    1/(theta H^2 K)), d_t_beg; stiff and resid (the particle-block relaxation's);
    inverse: per particle, the inverse of its bond block (solver.bonds_factor, the 21 entries
    of its lower triangle), a single row in a set made without bonds (`blocks` False: an
    unbonded simulation does not pay 168 bytes per particle for it)."""

    def __init__(self, capacity: int, particle_capacity: int, blocks: bool = True,
                 turn: bool = False):
        self.capacity, self.pool_args = capacity, (particle_capacity, blocks, turn)
        c = capacity
        self.inverse = ti.Vector.field(21, backend.real(), shape=particle_capacity if blocks else 1)
        # the particle-block relaxation's per-bond record (AoS), read whole at every visit
        (self.i, self.j, self.state, self.normal, self.impulse, self.cn, self.ct, self.rhs_n,
         self.rhs_t, self.stiff, self.resid, self.half_gap) = _struct(
            c, ti.field(ti.i32), ti.field(ti.i32), ti.field(ti.i32), _vec_row(), _vec_row(),
            _real_row(), _real_row(), _real_row(), _vec_row(),
            ti.Vector.field(4, backend.real()), _vec_row(), _real_row())
        # stiff: per step, (alpha, beta) of K = (C + W_o)^-1 seen from i, then from j
        # (solver.bonds_factor); resid: per sweep, the bond's residual seen from the particle
        # being relaxed
        self.g0, self.created, self.area = _real(c), _real(c), _real(c)
        self.d_t, self.hd_t, self.hk_t = _vec(c), _vec(c), _vec(c)
        self.hd_n, self.hk_n = _real(c), _real(c)
        self.broken_time, self.broken_pos = _real(c), _vec(c)
        self.d_t_beg = _vec(c)
        # the frame's turn over the step (SolverSettings.bond_frame = "end"): per bond, the
        # central tangential impulse that turns its normal force with the line of centres and
        # its coefficient (solver.solve_bond_turn), one slot each in a set made without it
        # (`turn` False: 70 B per particle on the study's shear); turn_on: 1 in a set made with
        # them (the kernels read them only then)
        tc = c if turn else 1
        self.turn, self.turn_k = _vec(tc), _real(tc)
        self.turn_on = _scalar()
        self.acc_p, self.acc_d = _vec(c), _vec(c)
        # the impulse of the step before the last (the extrapolated warm start)
        self.impulse_prev = _vec(c)
        self.start = _int(particle_capacity + 1)
        # bonds whose second particle is p: rev[rev_start[p]:rev_start[p + 1]] (the bonds of
        # particle p are bonds start[p]..start[p+1] plus these: the particle-block relaxation)
        self.rev = _int(c)
        self.rev_start = _int(particle_capacity + 1)
        self.total = _scalar()
        self.broken = _scalar()

    @property
    def has_turn(self) -> bool:
        """Whether the set holds the turn's fields (made for bond_frame = "end"): turn_on, as
        the host knows it without reading the field."""
        return self.pool_args[2]

    def reset(self):
        self.total[None] = 0
        self.broken[None] = 0
        self.turn_on[None] = int(self.has_turn)
        self.start.fill(0)
        self.rev_start.fill(0)


@field_record
class ColourSet:
    """Colouring of bonds + contacts (items: bonds first, then contacts). mask: per-body used
    colours (bit set); item_colour; order: items sorted by colour; start: CSR per colour;
    change: per item (|dR|, |R|) of the last sweep, for the residual."""

    def __init__(self, capacity: int, particle_capacity: int, systems: int = 1,
                 body_momentum: bool = False):
        self.capacity, self.pool_args = capacity, (particle_capacity, systems, body_momentum)
        self.systems = systems
        # the resident schedule's NNCG (solver.body_momentum), per particle within one step's
        # solve: the velocities at the start of the sweep, and the body part M^-1 H^T p of the
        # momentum direction p (one slot each when unused: 96 B per particle in f64)
        nb = particle_capacity if body_momentum else 1
        self.sweep_v, self.sweep_w, self.dir_v, self.dir_w = _vec(nb), _vec(nb), _vec(nb), _vec(nb)
        self.mask = ti.field(ti.u32, shape=(particle_capacity, COLOUR_WORDS))
        self.item_colour, self.order = _int(capacity), _int(capacity)
        self.start, self.cursor = _int(MAX_COLOURS + 1), _int(MAX_COLOURS)
        # within a colour the items are listed system by system: colour c's items of system sy
        # are order[sys_start[c * systems + sy] .. sys_start[c * systems + sy + 1] - 1]
        # (solver.solve_resident: a system's block reads its own items only); sys_cursor
        # places them (solver.colour_rounds_order)
        self.sys_start = _int(MAX_COLOURS * systems + 1)
        self.sys_cursor = _int(MAX_COLOURS * systems)
        self.change = ti.Vector.field(2, backend.real(), shape=capacity)
        # parallel colouring by rounds (solver.colour_round*): per body, the round that
        # claimed it and the best bid of the current pass; coloured/active item counts
        self.claim = _int(particle_capacity)
        self.best = _int(particle_capacity, ti.i64)
        self.coloured, self.active = _scalar(), _scalar()
        # solver.solve_colours_next: the colours of this step, and the next call's first one
        self.ncol, self.base = _scalar(), _scalar()
        # the residual's partial sums, one per chunk of RESIDUAL_CHUNK items
        # (solver.solve_resident: per system, after the chunks of the systems before it)
        self.partial = ti.Vector.field(2, backend.real(),
                                       shape=capacity // RESIDUAL_CHUNK + MAX_SYSTEMS + 2)
        # solver.solve_resident: each system's last residual and its decision to stop
        self.sys_residual = ti.field(backend.real(), shape=MAX_SYSTEMS)
        self.sys_stop = _int(MAX_SYSTEMS)
        # solver.solve_resident with NNCG: per chunk of MOMENTUM_CHUNK items the sweep's sum
        # |dR|^2, per system its MOMENTUM_GROUPS group sums, and its momentum factor
        self.gpartial = ti.field(backend.real(), shape=capacity // MOMENTUM_CHUNK + MAX_SYSTEMS + 2)
        self.ggroup = ti.field(backend.real(), shape=MAX_SYSTEMS * MOMENTUM_GROUPS)
        self.sys_beta = ti.field(backend.real(), shape=MAX_SYSTEMS)
        # the same for the 'Quad ' check's six sums (solver.quad_check_colours)
        self.qpartial = ti.Vector.field(6, backend.real(), shape=capacity // RESIDUAL_CHUNK + 2)
        self.residual = ti.field(backend.real(), shape=())

    def reset(self):
        pass


@field_record
class Partition:
    """Item lists of the partitioned (multi-thread) Gauss-Seidel, see tcd/partitioned.py.

    part: slab of each particle (0 .. parts-1); hist: work per bin across the sample (then the
    slab of each bin). Bond items (particle blocks or bonds) in `border` and contacts in
    `corder`, each as CSR lists over (slab 0, ..., slab parts-1, boundary): `bstart`, `cstart`
    (MAX_PARTS + 2 entries; `bcur`, `ccur` their fill cursors), canonical order in a list;
    intact bonds by the list of their momentum in `morder` (`mstart`, `mcur`).
    sums: per list (sum |dR|, sum |R|, sum |dR|^2) of the contacts in the current sweep;
    bsums: the same per bookkeeping unit (a range of bonds).
    claim, finished, released, stop: the workers' counters; beta, g2_prev, residual: the NNCG
    momentum and the last measured residual, shared between the workers."""

    def __init__(self, capacity: int, particle_capacity: int):
        self.capacity, self.pool_args = capacity, (particle_capacity,)
        self.part = _int(particle_capacity)
        self.hist = _int(SLAB_BINS)
        self.border, self.corder = _int(capacity), _int(capacity)
        self.bstart, self.cstart = _int(MAX_PARTS + 2), _int(MAX_PARTS + 2)
        self.bcur, self.ccur = _int(MAX_PARTS + 1), _int(MAX_PARTS + 1)
        self.morder = _int(capacity)
        self.mstart, self.mcur = _int(MAX_PARTS + 2), _int(MAX_PARTS + 1)
        self.sums = _vec(MAX_PARTS + 1)
        self.bsums = _vec(MAX_PARTS)
        self.claim, self.finished, self.released, self.stop = (_scalar(), _scalar(), _scalar(),
                                                              _scalar())
        self.beta, self.g2_prev, self.residual = (_scalar(backend.real()), _scalar(backend.real()),
                                                  _scalar(backend.real()))

    def reset(self):
        pass


@field_record
class SolverStats:
    """Per-step solver record: sweeps used, final residual, colours used; per batched system
    (sys_sweeps, sys_residual) and over all of them (sweeps: the most, residual: the largest)."""
    pool_args = ()

    def __init__(self, capacity: int = 1):
        self.capacity = capacity
        self.sweeps = _scalar()
        self.residual = _scalar(backend.real())
        self.sys_sweeps = _int(MAX_SYSTEMS)
        self.sys_residual = _real(MAX_SYSTEMS)
        self.colours = _scalar()
        self.colour_overflow = _scalar()
        # Simulation.quad_norms: the 'Quad ' norms of the current state
        self.quad = _real(3)

    def reset(self):
        self.sweeps[None] = 0
        self.residual[None] = 0.0


def field_bytes(obj) -> int:
    """Bytes held by the Taichi fields of a container (for memory reports)."""
    total = 0
    for v in vars(obj).values():
        if isinstance(v, ti.MatrixField):
            total += int(np.prod(v.shape)) * v.n * v.m * np.dtype(_np_dtype(v)).itemsize
        elif isinstance(v, ti.Field):
            total += int(np.prod(v.shape)) * np.dtype(_np_dtype(v)).itemsize
    return total
