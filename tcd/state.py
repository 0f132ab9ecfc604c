"""Field containers: particles, walls, the broad-phase grid, contacts and bonds.

Struct-of-arrays Taichi fields grouped in small data-oriented classes. A container is passed to
kernels as a template argument, so when a capacity-limited container overflows the simulation
builds a bigger one and the kernels are specialised for it; nothing is silently truncated.
All real fields use the precision chosen by `tcd.init`.
"""
from __future__ import annotations

import numpy as np
import taichi as ti

from . import backend

MAX_WALLS = 16
COLOUR_WORDS = 8            # 32-bit words of the per-body colour mask
MAX_COLOURS = 32 * COLOUR_WORDS


def _vec(n):
    return ti.Vector.field(3, backend.real(), shape=max(n, 1))


def _real(n):
    return ti.field(backend.real(), shape=max(n, 1))


def _int(n, dtype=ti.i32):
    return ti.field(dtype, shape=max(n, 1))


@ti.data_oriented
class Particles:
    """Rigid spheres. n: count. Model: radius (m), inv_mass (1/kg), inv_inertia (1/(kg m^2)),
    layer (0 bottom course, 1 top course), external force f_ext (N). State: x (m), v (m/s),
    w (rad/s); v_old, w_old hold the velocities at the beginning of the step."""

    def __init__(self, n: int):
        self.n = n
        self.x, self.v, self.w = _vec(n), _vec(n), _vec(n)
        self.v_old, self.w_old, self.f_ext = _vec(n), _vec(n), _vec(n)
        self.radius, self.inv_mass, self.inv_inertia = _real(n), _real(n), _real(n)
        self.layer = _int(n)


@ti.data_oriented
class WallFields:
    """Device copy of the walls: kind (0 plane, 1 cylinder), point, direction, radius, axial
    range lo/hi, friction, velocity over the current step (m/s) and force from the particles
    over the last step (N)."""

    def __init__(self):
        m = MAX_WALLS
        self.kind = _int(m)
        self.point, self.direction, self.velocity, self.force = _vec(m), _vec(m), _vec(m), _vec(m)
        self.radius, self.lo, self.hi, self.friction = _real(m), _real(m), _real(m), _real(m)
        self.count = ti.field(ti.i32, shape=())


@ti.data_oriented
class Grid:
    """Uniform grid for the broad phase (counting sort of particles by the cells their
    enlarged bounding box overlaps). origin (m), cell (m) and dims are compile-time constants
    of the kernels; items has capacity `capacity` (particle-cell incidences)."""

    def __init__(self, origin, cell: float, dims, capacity: int):
        self.origin = tuple(float(o) for o in origin)
        self.cell = float(cell)
        self.inv_cell = 1.0 / float(cell)
        self.dims = tuple(int(d) for d in dims)
        self.ncells = self.dims[0] * self.dims[1] * self.dims[2]
        self.capacity = capacity
        self.cell_count = _int(self.ncells)
        self.cell_start = _int(self.ncells + 1)
        self.items = _int(capacity)
        self.total = ti.field(ti.i32, shape=())


@ti.data_oriented
class Contacts:
    """Frictional contacts of one step, in canonical order: grouped by first particle i
    (ascending), then partner j ascending (particles, then walls as j = N + wall index).

    Per contact: i, j, normal n (i to j), g_beg (gap at the predicted configuration, m),
    rhs = max(g_beg, 0) / (theta H) (m/s), wnn, wtt (Delassus diagonal, 1/kg), mu, impulse R
    (N s, global vector), colour. Per particle: count and start (CSR). The previous step's
    (j, R, start) are kept in prev_* for warm starting."""

    def __init__(self, n: int, capacity: int):
        self.n, self.capacity = n, capacity
        c = capacity
        self.i, self.j, self.colour = _int(c), _int(c), _int(c)
        self.normal, self.impulse = _vec(c), _vec(c)
        self.gap, self.rhs, self.wnn, self.wtt, self.mu = _real(c), _real(c), _real(c), _real(c), _real(c)
        self.count, self.start = _int(n), _int(n + 1)
        self.prev_j, self.prev_impulse, self.prev_start = _int(c), _vec(c), _int(n + 1)
        self.total = ti.field(ti.i32, shape=())
        self.prev_total = ti.field(ti.i32, shape=())


@ti.data_oriented
class Bonds:
    """Bonded (Burgers) contacts: a fixed set sorted by (i, j), i < j, CSR start per particle.

    Model: i, j, g0 (gap at creation, m), created (time, s), area (pi min(r)^2, m^2).
    State: state (0 intact, 1 broken in tension, 2 broken in shear), impulse R (N s),
    d_t (tangential displacement, m, global vector in the tangent plane),
    Burgers history (normal: hd_n dashpot, hk_n Kelvin; tangential: hd_t, hk_t, m),
    broken_time (s, NaN while intact), broken_pos (m).
    Per step: normal, rhs_n, rhs_t (displacement terms / (theta H)), cn, ct (extra compliance
    1/(theta H^2 K)), wnn, wtt, d_t_beg."""

    def __init__(self, n: int, capacity: int):
        self.n, self.capacity = n, capacity
        c = capacity
        self.i, self.j, self.state = _int(c), _int(c), _int(c)
        self.g0, self.created, self.area = _real(c), _real(c), _real(c)
        self.impulse, self.d_t, self.hd_t, self.hk_t = _vec(c), _vec(c), _vec(c), _vec(c)
        self.hd_n, self.hk_n = _real(c), _real(c)
        self.broken_time, self.broken_pos = _real(c), _vec(c)
        self.normal, self.rhs_t, self.d_t_beg = _vec(c), _vec(c), _vec(c)
        self.rhs_n, self.cn, self.ct, self.wnn, self.wtt = _real(c), _real(c), _real(c), _real(c), _real(c)
        self.start = _int(n + 1)
        self.total = ti.field(ti.i32, shape=())


@ti.data_oriented
class ColourSet:
    """Colouring of bonds + contacts (items: bonds first, then contacts). mask: per-body used
    colours (bit set); item_colour; order: items sorted by colour; start: CSR per colour;
    change: per item (|dR|, |R|) of the last sweep, for the residual."""

    def __init__(self, n: int, capacity: int):
        self.n, self.capacity = n, capacity
        self.mask = ti.field(ti.u32, shape=(max(n, 1), COLOUR_WORDS))
        self.item_colour, self.order = _int(capacity), _int(capacity)
        self.start, self.cursor = _int(MAX_COLOURS + 1), _int(MAX_COLOURS)
        self.change = ti.Vector.field(2, backend.real(), shape=max(capacity, 1))


@ti.data_oriented
class SolverStats:
    """Per-step solver record: sweeps used, final residual, colours used."""

    def __init__(self):
        self.sweeps = ti.field(ti.i32, shape=())
        self.residual = ti.field(backend.real(), shape=())
        self.colours = ti.field(ti.i32, shape=())
        self.colour_overflow = ti.field(ti.i32, shape=())


def field_bytes(obj) -> int:
    """Bytes held by the Taichi fields of a container (for memory reports)."""
    total = 0
    for v in vars(obj).values():
        if isinstance(v, (ti.Field, ti.MatrixField)):
            total += int(np.prod(v.shape)) * (v.n * v.m if isinstance(v, ti.MatrixField) else 1) * \
                     (8 if v.dtype in (ti.f64, ti.i64, ti.u64) else 4)
    return total
