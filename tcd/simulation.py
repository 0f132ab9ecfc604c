"""One Contact Dynamics system: particles, walls, contacts, bonds, and the time step.

`Simulation.step()` reads like the algorithm (Moreau-Jean with NLGS, PHYSICS.md section 2):
    walls: velocity over [t, t+H] from their prescribed motion
    broad phase (grid) and contacts at the current configuration, warm-started
    bonds: frame, compliance, displacement terms
    v_free = v + H M^-1 f ; apply warm-start impulses
    NLGS sweeps (serial or coloured schedule) until converged
    bonds: tangential displacement, Burgers history, yield
    x += H (theta v+ + (1 - theta) v-) ; wall forces ; t += H
It holds no arithmetic of its own beyond bookkeeping: kernels live in contacts.py / solver.py.
"""
from __future__ import annotations

import dataclasses
import math
import os
import warnings
from typing import Sequence

import numpy as np

from . import backend, contacts as ck, partitioned as pk, solver as sk, state as state_mod
from .state import (MAX_PARTS, MAX_SWEEPS, MAX_SYSTEMS, MAX_WALLS, Bonds, ColourSet, Contacts, Grid, Neighbours, Partition,
                    Particles, SolverStats, WallFields, acquire, capacity_class, field_bytes, get, get_fields, put, put_fields,
                    release)
from .stack import user_stacklevel
from .walls import KINDS, Wall

SCHEDULES = ("auto", "serial", "partitioned", "coloured", "resident")
COLOURED = ("coloured", "resident")     # the schedules that colour their items
ACCELERATIONS = ("nncg", "none")
SWEEP_ORDERS = ("forward", "symmetric")
BOND_FRAMES = ("start", "end")
CONVERGENCE_MEASURES = ("impulse", "quad")
COLOURINGS = ("auto", "greedy", "rounds")
INT32_MAX = 2**31 - 1
# the particles' arrays of a state (Simulation.state_dict; "particles/system" besides in a batch)
PARTICLE_STATE = ("x", "v", "w", "radius", "layer", "inv_mass", "inv_inertia", "f_ext")
# what load_state_dict needs of a state (state_dict writes these and more)
STATE_KEYS = tuple("particles/" + k for k in PARTICLE_STATE) + tuple(
    "contacts/" + k for k in ("i", "j", "impulse", "gap", "start")) + ("bonds/state",)


def _auto_arch() -> str:
    """The backend whose defaults "auto" settings follow: the one running, unless the
    environment variable TCD_AUTO=gpu asks for the GPU's choices (coloured schedule, colouring
    by rounds) on the CPU, to run the GPU's algorithms where no GPU is."""
    auto = os.environ.get("TCD_AUTO", "")
    if auto not in ("", "cpu", "gpu"):
        raise ValueError(f"TCD_AUTO={auto!r}: expected 'cpu' or 'gpu'")
    return auto or backend.arch()


def _colours_per_launch() -> int:
    """Colours unrolled into one solve call of the coloured schedule: solver.COLOURS_PER_LAUNCH,
    or the environment variable TCD_COLOURS_PER_LAUNCH (1 to 16), for measuring the GPU's
    launch costs (each value compiles its own kernel; the numbers are the same for any). Read
    when a Simulation is made."""
    text = os.environ.get("TCD_COLOURS_PER_LAUNCH", "")
    if not text:
        return sk.COLOURS_PER_LAUNCH
    try:
        k = int(text)
    except ValueError:
        k = 0
    if not 1 <= k <= 16:
        raise ValueError(f"TCD_COLOURS_PER_LAUNCH={text!r}: expected an integer from 1 to 16")
    return k


def _solve_base_in_field() -> bool:
    """The environment variable TCD_SOLVE_BASE: "arg" (default: each solve call of the
    coloured schedule gets its first colour as an argument, solver.solve_colours) or "field"
    (read from the colour set and advanced on the device, solver.solve_colours_next: calls
    without a runtime argument), for measuring a GPU's launch costs; the same numbers. Read
    when a Simulation is made."""
    text = os.environ.get("TCD_SOLVE_BASE", "") or "arg"
    if text not in ("arg", "field"):
        raise ValueError(f"TCD_SOLVE_BASE={text!r}: expected 'arg' or 'field'")
    return text == "field"


def per_particle(name: str, values, n: int, *, broadcast: bool = True) -> np.ndarray:
    """`values` as an (n, 3) float array: one 3-vector per particle, or (`broadcast`) one for
    all; ValueError naming `name` for any other shape (a shorter array was zero-padded, a
    longer one cut) or for NaN and infinite entries (they spread through every later step)."""
    arr = np.asarray(values, dtype=float)
    if broadcast and arr.shape == (3,):
        arr = np.broadcast_to(arr, (n, 3))
    if arr.shape != (n, 3):
        want = f"({n}, 3) or (3,)" if broadcast else f"({n}, 3)"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite (got NaN or infinity at particle "
                         f"{int(np.argwhere(~np.isfinite(arr))[0, 0])})")
    return np.array(arr)


def _numbers(name: str, values) -> np.ndarray:
    """`values` as a float array; ValueError naming `name` if they are not numbers."""
    try:
        return np.asarray(values, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numbers: {exc}") from None


def _check_distinct_centres(position: np.ndarray, system: np.ndarray) -> None:
    """ValueError naming two particles of one system at the same centre: their contact has no
    normal (the systems of a batch may overlap in space: they never meet)."""
    keyed = np.column_stack([system.astype(float), position])
    order = np.lexsort(keyed.T[::-1])
    same = np.all(keyed[order[1:]] == keyed[order[:-1]], axis=1)
    if same.any():
        k = int(np.argmax(same))
        i, j = sorted((int(order[k]), int(order[k + 1])))
        raise ValueError(f"particles {i} and {j} have the same centre {position[i].tolist()} m: "
                         "their contact has no normal")


def _finite(name: str, value, *, low=None, positive=False) -> None:
    """ValueError unless `value` is a finite number (>= low, or > 0 with `positive`); a
    string ("1e-4") or a bool is not a number here (it was stored as given, and failed later
    in arithmetic far from its name)."""
    if isinstance(value, (bool, np.bool_, str, bytes)) or not isinstance(value, (int, float, np.number)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        ok = math.isfinite(float(value))
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not ok or (positive and not float(value) > 0) or (low is not None and float(value) < low):
        need = "positive and finite" if positive else (f"finite and >= {low}" if low is not None
                                                       else "finite")
        raise ValueError(f"{name} must be {need}, got {value!r}")


def _check_permutation(name: str, a: np.ndarray) -> None:
    """Refuse integers `a` that are not a permutation of 0..len(a)-1."""
    if not np.array_equal(np.sort(a), np.arange(len(a))):
        raise ValueError(f"{name} is not a permutation of 0..{len(a) - 1}")


def _integer(name: str, value, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not low <= value <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")


class CapacityError(RuntimeError):
    """A buffer could not hold what the step needs and could not grow."""


def _check_on_backend(settings) -> None:
    """Settings the backend cannot run: bond_frame = "end" in f32."""
    if settings.bond_frame == "end" and backend.precision() == "f32":
        from .config import BOND_FRAME_F32
        raise ValueError(f"bond_frame: {BOND_FRAME_F32}")


@dataclasses.dataclass(frozen=True)
class SolverSettings:
    """time_step H (s); theta of the Moreau-Jean scheme in [0.5, 1]; tolerance on the
    convergence measure; convergence: the measure, "impulse" (the relative impulse change of
    a sweep, sum |dR| / sum |R|: PHYSICS.md section 6, the default and the measure of every
    shipped result) or "quad" (LMGC90's 'Quad ' check: a pass that updates nothing and
    measures the velocity corrections the local solves would still make, relative to those of
    the impulses; the largest of its QuadDV, QuadDVR and |MeanDVoR|: tcd/solver.py);
    max_sweeps; check_every (sweeps between convergence checks);
    schedule: "serial", "partitioned" (the serial sweep split over `threads` CPU threads:
    tcd/partitioned.py; its numbers depend on `threads`), "coloured", "resident" (the coloured
    schedule's colours with all sweeps of a step in one launch, one GPU thread block per
    system: solver.solve_resident; each system to its own convergence; no "quad" check) or
    "auto" (serial on CPU, coloured on GPU); threads: parts of the partitioned schedule; acceleration:
    "nncg" (nonsmooth nonlinear conjugate gradient on top of the Gauss-Seidel sweeps of the
    serial, partitioned and resident schedules) or "none" (plain Gauss-Seidel; the coloured
    schedule is always plain); sweep_order:
    "symmetric" (forward and backward sweeps alternate: the default, and the order of every
    shipped result) or "forward" (every sweep in item order: fewer sweeps on the shear, 25.0
    against 34.4 per step, but larger overlaps under the vibrating plate of a preparation:
    docs/performance.md); the coloured and resident schedules always sweep their colours
    forward;
    warm_start_extrapolation c in [0, 1]: each bond, and each contact that carried an impulse
    at the last two steps, starts the step from R_n + c (R_n - R_n-1) instead of R_n (0, the
    default and the setting of every shipped result: the last impulse; the stopping rule is
    the same, only the starting point moves: docs/performance.md);
    alert_ratio:
    alert distance as a fraction of the smallest radius; gravity (m/s^2, vector);
    overlap_slop: interpenetration (fraction of the smallest diameter) left alone by the
    end-of-step position projection; projection_passes: its sweeps per step (0: off);
    bond_blocks: relax the bonds particle by particle, each particle's bonds solved exactly
    (both schedules; False: bond by bond, which converges badly on light grains);
    bond_frame: "start" (a bond's normal force acts along the line of centres of the step's
    start: the default, and the setting of every shipped result) or "end" (turned with the
    line of centres over the step, implicitly in the velocities: solver.solve_bond_turn; a
    grain rolling about one loaded bond is then stable at any time step, where "start" needs
    F H^2 / (m L) below 5.6: docs/physics.md, "Limitations"; needs acceleration = "none");
    neighbour_skin: skin of the broad phase's neighbour list as a fraction of the smallest
    radius (contacts are picked from the list every step, the grid is only walked when a
    particle may have moved more than its margin, half the skin or three steps of its reach
    for a fast grain; the contacts are the same for any skin, only the cost changes);
    colouring (coloured schedule): "greedy" (one thread, canonical order: fewest colours),
    "rounds" (in parallel, solver.colour_round: a few more colours, no serial pass) or
    "auto" (greedy on the CPU, rounds on the GPU)."""
    time_step: float = 2e-4
    theta: float = 1.0
    tolerance: float = 1e-4
    max_sweeps: int = 1000
    check_every: int = 1
    convergence: str = "impulse"
    schedule: str = "auto"
    threads: int = 2
    acceleration: str = "nncg"
    sweep_order: str = "symmetric"
    warm_start_extrapolation: float = 0.0
    alert_ratio: float = 0.1
    gravity: tuple = (0.0, 0.0, -9.81)
    overlap_slop: float = 0.002
    projection_passes: int = 2
    bond_blocks: bool = True
    bond_frame: str = "start"
    neighbour_skin: float = 2.0
    colouring: str = "auto"

    def __post_init__(self):
        _finite("time_step", self.time_step, positive=True)
        _finite("theta", self.theta)
        if not 0.5 <= self.theta <= 1.0:
            raise ValueError(f"theta must be in [0.5, 1], got {self.theta}")
        _finite("tolerance", self.tolerance, positive=True)
        # integers handed to the kernels as 32-bit arguments
        _integer("max_sweeps", self.max_sweeps, 1, MAX_SWEEPS)
        _integer("check_every", self.check_every, 1, INT32_MAX)
        _integer("threads", self.threads, 1, MAX_PARTS)
        _integer("projection_passes", self.projection_passes, 0, INT32_MAX)
        _finite("overlap_slop", self.overlap_slop, low=0.0)
        _finite("alert_ratio", self.alert_ratio, positive=True)
        _finite("neighbour_skin", self.neighbour_skin, low=0.0)
        _finite("warm_start_extrapolation", self.warm_start_extrapolation, low=0.0)
        if self.warm_start_extrapolation > 1.0:
            raise ValueError("warm_start_extrapolation must be in [0, 1], got "
                             f"{self.warm_start_extrapolation}")
        g = list(self.gravity) if np.ndim(self.gravity) == 1 else None
        if (g is None or len(g) != 3 or not all(
                isinstance(c, (int, float, np.integer, np.floating)) and not isinstance(c, bool)
                and math.isfinite(float(c)) for c in g)):
            raise ValueError(f"gravity must be a finite 3-vector of numbers (m/s^2), got "
                             f"{self.gravity!r}")
        if not isinstance(self.bond_blocks, (bool, np.bool_)):
            raise ValueError(f"bond_blocks must be True or False, got {self.bond_blocks!r}")
        # stored as Python numbers: a NumPy scalar kept its type in the clock's arithmetic (an
        # np.float32 time step made the time float32, which stops advancing near 2048 s) and an
        # array or list of gravity made the settings unequal or unhashable (session 69)
        for name in _SETTINGS_FLOATS:
            object.__setattr__(self, name, float(getattr(self, name)))
        for name in _SETTINGS_INTS:
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "gravity", tuple(float(c) for c in g))
        object.__setattr__(self, "bond_blocks", bool(self.bond_blocks))
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {SCHEDULES}, got {self.schedule!r}")
        if self.colouring not in COLOURINGS:
            raise ValueError(f"colouring must be one of {COLOURINGS}, got {self.colouring!r}")
        if self.acceleration not in ACCELERATIONS:
            raise ValueError(f"acceleration must be one of {ACCELERATIONS}, got "
                             f"{self.acceleration!r}")
        if self.bond_frame not in BOND_FRAMES:
            raise ValueError(f"bond_frame must be one of {BOND_FRAMES}, got {self.bond_frame!r}")
        if self.bond_frame == "end" and self.acceleration != "none":
            # the momentum moves the bonds' impulses but not their turns, and the sweeps
            # diverge (seen in f32, where rounding starts them: session 45)
            raise ValueError(f"bond_frame = \"end\" needs acceleration = \"none\" (got "
                             f"{self.acceleration!r}): the conjugate-gradient momentum does not "
                             "move the bonds' turns, and with it the sweeps diverge")
        if self.sweep_order not in SWEEP_ORDERS:
            raise ValueError(f"sweep_order must be one of {SWEEP_ORDERS}, got "
                             f"{self.sweep_order!r}")
        if self.convergence not in CONVERGENCE_MEASURES:
            raise ValueError(f"convergence must be one of {CONVERGENCE_MEASURES}, got "
                             f"{self.convergence!r}")


_SETTINGS_FLOATS = ("time_step", "theta", "tolerance", "overlap_slop", "alert_ratio",
                    "neighbour_skin", "warm_start_extrapolation")
_SETTINGS_INTS = ("max_sweeps", "check_every", "threads", "projection_passes")


@dataclasses.dataclass(frozen=True)
class BondLaw:
    """Burgers bond parameters (SI) and yield. mode: "paper" (secant K = 1/J(age)) or
    "burgers" (incremental four-parameter model). Tangential parameters are the normal ones
    divided by 2 (1 + poisson_ratio)."""
    mode: str = "paper"
    maxwell_stiffness: float = 2e6
    maxwell_viscosity: float = 2e7
    kelvin_stiffness: float = 2e6
    kelvin_viscosity: float = 2e7
    poisson_ratio: float = 0.3
    yield_stress: float = 2.7e6
    friction_after_break: float = 0.7

    def __post_init__(self):
        if self.mode not in ("paper", "burgers"):
            raise ValueError(f"bond mode must be 'paper' or 'burgers', got {self.mode!r}")
        for f in ("maxwell_stiffness", "maxwell_viscosity", "kelvin_stiffness", "kelvin_viscosity",
                  "yield_stress"):
            _finite(f"bond {f}", getattr(self, f), positive=True)
        _finite("bond friction_after_break", self.friction_after_break, low=0.0)
        _finite("poisson_ratio", self.poisson_ratio)
        if not -1.0 < self.poisson_ratio < 0.5:
            raise ValueError(f"poisson_ratio must be in (-1, 0.5), got {self.poisson_ratio}")
        for f in ("maxwell_stiffness", "maxwell_viscosity", "kelvin_stiffness", "kelvin_viscosity",
                  "poisson_ratio", "yield_stress", "friction_after_break"):
            object.__setattr__(self, f, float(getattr(self, f)))     # (as SolverSettings)

    @property
    def tangent_factor(self) -> float:
        return 2.0 * (1.0 + self.poisson_ratio)


@dataclasses.dataclass
class StepRecord:
    time: float
    sweeps: int
    residual: float
    contacts: int
    colours: int
    bonds_intact: int


def default_cell_size(radius, alert: float, margin: float) -> float:
    """Grid cell size (m) for spheres of these radii: each sphere is listed in every cell its
    box (side s = 2 (r + alert / 2 + margin)) overlaps, on average (s / c + 1)^3 cells of side
    c, and a neighbour-list build checks, per sphere, the items of each of its cells: about
    c^3 mean((s / c + 1)^3)^2 pair checks per unit of volume. The c that minimises it lies
    between the smallest and the largest box (for equal spheres, c = s); with the paper's
    binder course (diameters 2 to 16 mm) about 11 mm, where the smallest diameter times 4.4
    made twice the checks and 7 times the grid items of the 2.6 mm wide boxes' optimum."""
    s = 2.0 * (np.asarray(radius, float) + 0.5 * alert + margin)
    if s.size > 20000:                       # the mean is all that counts: a fixed subsample
        s = np.sort(s)[np.linspace(0, s.size - 1, 20000).astype(int)]
    cells = np.geomspace(s.min(), s.max(), 48) if s.max() > s.min() else s[:1]
    work = [c**3 * np.mean((s / c + 1.0) ** 3) ** 2 for c in cells]
    return float(cells[int(np.argmin(work))])


MAX_GRID_CELLS = 64_000_000
#: the largest first contact buffer a Simulation accepts (slots; it grows on overflow anyway)
MAX_CONTACT_CAPACITY = 2**27


class GridTooLarge(ValueError):
    """The broad phase's grid would have more than MAX_GRID_CELLS cells."""


class WallList(list):
    """`Simulation.walls`: the walls the solver sees, read-only. An edit of it in place (an
    item assigned, a wall appended) would change what `walls`, `state_dict` and the saved
    frames report but not what the grains meet; it is refused, naming the methods that do
    both. Otherwise a list: `sim.walls + [wall]`, `list(sim.walls)` and comparisons work."""
    def _refuse(self, *args, **kwargs):
        raise TypeError("Simulation.walls is read-only: change a wall with "
                        "sim.replace_wall(k, wall), all of them with sim.set_walls([...])")

    __setitem__ = __delitem__ = __iadd__ = __imul__ = _refuse
    append = extend = insert = pop = remove = clear = sort = reverse = _refuse

    def __reduce__(self):           # a copy or a pickle rebuilds it whole, without append
        return (WallList, (list(self),))


class Simulation:
    """Rigid spheres between kinematic walls, stepped by Contact Dynamics.

    radius (N,) m, position (N,3) m; density (kg/m^3); layer (N,) ints;
    walls: list of `Wall`; friction: particle-particle Coulomb coefficient; domain: (lo, hi)
    corners (m) of the broad-phase grid (particles outside are clamped to its border cells);
    cell_size (m) of the grid (default: `default_cell_size`, the size that makes the fewest
    pair checks for these radii; any size gives the same contacts).
    `fixed` (N,) bools make particles kinematic (infinite mass, velocity kept).
    `system` (N,) ints 0..S-1, non-decreasing: S independent systems batched in one simulation
    (see `Simulation.batch`); particles of two systems never interact, and a wall tagged with
    a system (`Wall.system`) only touches that system's particles.
    """

    def __init__(self, radius, position, *, walls: Sequence[Wall] = (), density: float = 2600.0,
                 layer=None, velocity=None, fixed=None, friction: float = 0.7,
                 settings: SolverSettings = SolverSettings(), bond_law: BondLaw = BondLaw(),
                 domain=None, cell_size: float | None = None, contact_capacity: int | None = None,
                 time: float = 0.0, system=None):
        backend._require()
        if radius is None or position is None:
            raise TypeError("Simulation needs the radii and the positions of its particles, "
                            f"got radius={radius!r}, position={position!r}")
        walls = () if walls is None else walls
        radius = _numbers("radius", radius)
        if radius.ndim > 1:
            raise ValueError(f"radius must be one number per particle (shape (n,)), got shape "
                             f"{radius.shape}")
        radius = radius.reshape(-1)
        n = len(radius)
        if n == 0:
            raise ValueError("a simulation needs at least one particle")
        # (n, 3) exactly: a transposed (3, n) array is refused, not silently reshaped
        position = _numbers("position", position)
        if position.shape != (n, 3):
            raise ValueError(f"position must have shape ({n}, 3) (one row x, y, z per particle), "
                             f"got {position.shape}")
        if not np.all(np.isfinite(radius)) or np.any(radius <= 0):
            raise ValueError("every particle radius must be positive and finite")
        if not np.all(np.isfinite(position)):
            raise ValueError("particle positions must be finite")
        _finite("density", density, positive=True)
        _finite("friction", friction, low=0.0)
        _finite("time", time)
        if not isinstance(settings, SolverSettings):
            raise TypeError(f"settings must be a SolverSettings, got {type(settings).__name__}")
        _check_on_backend(settings)
        if not isinstance(bond_law, BondLaw):
            raise TypeError(f"bond_law must be a BondLaw, got {type(bond_law).__name__}")
        if layer is not None:
            layer = np.asarray(layer)
            if layer.shape != (n,) or not np.issubdtype(layer.dtype, np.integer):
                raise ValueError(f"layer must be {n} integers (one per particle), got shape "
                                 f"{layer.shape}, dtype {layer.dtype}")
            if layer.size and (layer.min() < 0 or layer.max() > INT32_MAX):
                raise ValueError("layer ids must be in [0, 2^31)")
        if cell_size is not None:
            _finite("cell_size", cell_size, positive=True)
        if contact_capacity is not None:
            _integer("contact_capacity", contact_capacity, 1, MAX_CONTACT_CAPACITY)
        if domain is not None:
            try:
                box = np.asarray(domain, dtype=float)
            except (TypeError, ValueError):
                box = None
            if box is None or box.shape != (2, 3) or not np.all(np.isfinite(box)) \
                    or not np.all(box[0] < box[1]):
                raise ValueError("domain must be two finite corners ((x0, y0, z0), (x1, y1, z1)) "
                                 f"with x0 < x1, y0 < y1, z0 < z1, got {domain!r}")
        velocity = (np.zeros((n, 3)) if velocity is None
                    else per_particle("velocity", velocity, n))     # one for all, as set_velocities
        if fixed is not None:
            fixed = np.asarray(fixed)
            if fixed.shape != (n,) or fixed.dtype != bool:
                raise ValueError(f"fixed must be {n} booleans (one per particle), got shape "
                                 f"{fixed.shape}, dtype {fixed.dtype}")
        system = np.zeros(n, np.int32) if system is None else np.asarray(system).reshape(-1)
        if system.shape != (n,) or not np.issubdtype(system.dtype, np.integer):
            raise ValueError(f"system must be {n} integers, got shape {system.shape}, dtype {system.dtype}")
        if system[0] != 0 or np.any(np.diff(system) < 0) or np.any(np.diff(system) > 1):
            raise ValueError("system ids must start at 0 and never decrease or skip a value "
                             "(each system's particles contiguous)")
        self.systems = int(system[-1]) + 1
        if self.systems > MAX_SYSTEMS:
            raise ValueError(f"at most {MAX_SYSTEMS} systems in one simulation, got {self.systems}")
        _check_distinct_centres(position, system)
        self.n = n
        self._settings = settings
        self.bond_law = bond_law
        self.friction = float(friction)
        self.density = float(density)
        self.time = float(time)
        self.step_index = 0
        self.r_min = float(radius.min())
        self.alert = settings.alert_ratio * self.r_min
        # the coloured schedule's launch shape (environment, for GPU measurements), read once
        self._per_launch = _colours_per_launch()
        # the resident schedule's block (threads, loop iterations) per system, read once
        self._resident_shape = ((sk.resident_threads(), sk.resident_spread())
                                if settings.schedule == "resident" else (1, 1))
        # and its NNCG momentum (2: the bodies' own, 1: over the colours), read once
        self._resident_momentum = (sk.resident_momentum() if settings.schedule == "resident"
                                   else 0)
        self._base_in_field = _solve_base_in_field()
        self.schedule = settings.schedule
        if self.schedule == "auto":
            self.schedule = "serial" if _auto_arch() == "cpu" else "coloured"
        if self.schedule == "partitioned" and backend.arch() != "cpu":
            raise ValueError("the partitioned schedule runs CPU threads that wait for each other; "
                             "on the GPU use schedule = \"coloured\" (or \"auto\")")
        if self.schedule == "resident" and settings.convergence == "quad":
            raise ValueError("the resident schedule measures convergence as the coloured one "
                             "does without its 'Quad ' check: use convergence = \"impulse\", or "
                             "schedule = \"coloured\" for convergence = \"quad\"")
        if self.schedule == "partitioned" and self.systems > 1:
            raise ValueError("the partitioned schedule splits ONE system over threads; a batch of "
                             f"{self.systems} systems already runs one thread per system on the "
                             "serial schedule: use schedule = \"serial\"")

        # the broad phase's box and cells, checked before any field is made (a failed field
        # allocation leaves Taichi's field tree unusable for the rest of the process)
        if domain is None:
            domain = (position.min(axis=0) - radius.max(), position.max(axis=0) + radius.max())
        self.domain = (np.asarray(domain[0], float), np.asarray(domain[1], float))
        self._cell_size_given = bool(cell_size)
        self.cell_size = (float(cell_size) if cell_size else
                          default_cell_size(radius, self.alert, self._half_skin))
        self.cell_size = max(self.cell_size, 1e-9)
        self._grid_dims()

        with np.errstate(over="ignore", divide="ignore", under="ignore", invalid="ignore"):
            mass = density * 4.0 / 3.0 * math.pi * radius**3
            inv_mass = 1.0 / mass
            inv_inertia = 1.0 / (0.4 * mass * radius**2)
            stored = [v.astype(backend.numpy_real()) for v in (inv_mass, inv_inertia)]
            usable = np.logical_and.reduce([(v > 0) & np.isfinite(v) for v in stored])
        if fixed is not None:
            fixed = np.asarray(fixed, dtype=bool)
            inv_mass[fixed] = 0.0
            inv_inertia[fixed] = 0.0
            usable |= fixed
        if not usable.all():
            # (a mass of 0 or infinity in the backend's precision: inverse masses of infinity
            # made NaN at the first step, of 0 a grain that no contact moves)
            k = int(np.argmin(usable))
            raise ValueError(f"density {float(density)!r} kg/m^3 and radius {float(radius[k])!r} "
                             f"m (particle {k}) give a mass of {float(mass[k])!r} kg, whose "
                             "inverse or that of its "
                             f"moment of inertia is not a positive finite {backend.precision()} "
                             "number")
        self.particles = acquire(Particles, n)
        p = self.particles
        p.count[None] = n
        layer = np.zeros(n, np.int32) if layer is None else np.asarray(layer, np.int32)
        put_fields(p, {"radius": radius, "inv_mass": inv_mass, "inv_inertia": inv_inertia,
                       "x": position, "v": velocity, "w": np.zeros((n, 3)),
                       "f_ext": np.zeros((n, 3)), "layer": layer,
                       "system": system.astype(np.int32)})
        self._inverse_masses = None         # inverse_masses(): read when first asked
        self.system_start = np.searchsorted(system, np.arange(self.systems + 1)).astype(np.int32)
        put(p.sys_start, self.system_start)
        # each particle's index in its sample (load_state_dict sets a renumbered state's)
        self.sample_index = self._identity_index()
        p.systems[None] = self.systems

        self.wall_fields = acquire(WallFields, MAX_WALLS)
        self._walls = WallList()
        self.set_walls(walls)

        self.grid = self._make_grid(self._grid_capacity_estimate(radius))
        # a settled bed has about 3 contacts per sphere (walls included): the buffer grows if not
        cap = contact_capacity if contact_capacity else max(64, 4 * n)
        self.contacts = acquire(Contacts, cap, self.particles.capacity)
        self.neighbours = acquire(Neighbours, 2 * cap, self.particles.capacity)
        self._neighbours_valid = False
        self.neighbour_builds = 0
        self.bonds = self._bond_buffer(0)
        self.colours = None
        self.partition = None
        self.stats = acquire(SolverStats, 1)
        self.last = StepRecord(self.time, 0, 0.0, 0, 0, 0)
        self.grow_events: list[str] = []
        self._refit_contacts = False

    # ---------------------------------------------------------------- construction helpers
    def _grid_dims(self) -> np.ndarray:
        """The grid's cells along x, y, z for the domain and cell size; GridTooLarge (before
        anything is allocated) when they are too many. Counted in Python integers: NumPy's
        product of three int64 overflowed for a cell of 1e-9 m, and slipped past the check."""
        lo, hi = self.domain
        dims = [max(1, math.ceil(float(e) / self.cell_size)) for e in (hi - lo)]
        ncells = math.prod(dims)
        if ncells > MAX_GRID_CELLS:
            ext = ", ".join(f"{1e3 * e:.4g}" for e in (np.asarray(hi) - np.asarray(lo)))
            shown = dims if max(dims) < 10**12 else [f"{d:.3g}" for d in map(float, dims)]
            raise GridTooLarge(f"broad-phase grid of {shown} cells (at most "
                               f"{MAX_GRID_CELLS:.3g}) is too large: a domain of ({ext}) mm in "
                               f"cells of {1e3 * self.cell_size:.4g} mm "
                               + ("(the cell_size given)" if self._cell_size_given else
                                  "(about the largest grain's diameter)")
                               + ": shrink the domain, or give a larger cell_size")
        if ncells * self.systems >= 2**31:
            raise ValueError(f"{self.systems} systems of {ncells} cells overflow the 32-bit cell "
                             "indices: enlarge cell_size or batch fewer systems")
        return np.array(dims, dtype=np.int64)

    def _make_grid(self, capacity: int) -> Grid:
        lo, hi = self.domain
        dims = self._grid_dims()
        ncells = int(np.prod(dims))
        # about 4 buckets per particle up to the number of cells (a power of two: c mod 2^k),
        # and at least the smallest capacity class, so that small simulations share their
        # grid and its kernels (state.MIN_SLOTS; the buckets past the cells stay empty). 8 per
        # particle (sessions 3-37) cost 45 B per particle more on the seed-1 shear (65536
        # buckets against 32768), for the same contacts and no measurable time
        buckets = 64
        while buckets < max(min(4 * self.n, ncells), state_mod.MIN_SLOTS):
            buckets *= 2
        grid = acquire(Grid, capacity, buckets)
        grid.configure(lo, self.cell_size, dims, buckets)
        return grid

    _POOLED = ("particles", "wall_fields", "grid", "neighbours", "contacts", "bonds", "colours",
               "partition", "stats")

    def close(self) -> None:
        """Hand the fields back to the pool for the next simulation (done on deletion too)."""
        for name in self._POOLED:
            release(self.__dict__.pop(name, None))
        self.__dict__["_closed"] = True

    def __getattr__(self, name):
        # only reached when `name` is not set: after close(), its fields are gone
        if name in Simulation._POOLED and self.__dict__.get("_closed"):
            raise RuntimeError("this Simulation was closed (close() handed its fields back to the "
                               "pool): make a new one")
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    @property
    def _half_skin(self) -> float:
        """Half the neighbour list's skin (m): the margin of a grain at rest."""
        return 0.5 * self.settings.neighbour_skin * self.r_min

    def _grid_capacity_estimate(self, radius) -> int:
        # each box: radius + half the alert distance + the neighbour list's margin (half the
        # skin for a grain at rest); a box of side s overlaps (s / cell + 1)^3 cells on average
        span = 2.0 * (radius + 0.5 * self.alert + self._half_skin) / self.cell_size + 1.0
        return int(np.sum(span ** 3) * 1.15) + 64

    # settings the simulation is built with (its schedule's data, its contacts' alert distance,
    # its bonds' turn fields)
    BUILT_WITH = ("schedule", "alert_ratio", "bond_frame")

    @property
    def walls(self) -> WallList:
        """The walls, in order (read-only: `set_walls`, `replace_wall`)."""
        return self._walls

    @property
    def settings(self) -> SolverSettings:
        """The solver settings. A new SolverSettings may replace them between steps (the next
        step runs with its time step, tolerance, sweeps...), except for BUILT_WITH, which the
        simulation was built with: changing those needs a new Simulation."""
        return self._settings

    @settings.setter
    def settings(self, new: SolverSettings) -> None:
        if not isinstance(new, SolverSettings):
            raise TypeError(f"settings must be a SolverSettings, got {type(new).__name__}")
        fixed = [f"{k} ({getattr(self._settings, k)!r} -> {getattr(new, k)!r})"
                 for k in self.BUILT_WITH if getattr(new, k) != getattr(self._settings, k)]
        if fixed:
            raise ValueError(f"settings {', '.join(fixed)}: fixed when the simulation was built; "
                             "build a new Simulation with them (from sim.state_dict())")
        _check_on_backend(new)
        self._settings = new

    def set_walls(self, walls: Sequence[Wall]) -> None:
        """Replace the walls (e.g. mould -> split shear box). Wall contacts lose their history.
        A warning names the walls that have particle centres on their wrong side (outside a
        cylinder, behind a plane): the contact law pushes those particles through."""
        if isinstance(walls, Wall):
            raise ValueError("walls must be a list of walls: got one Wall (write [wall])")
        walls = list(walls)
        if len(walls) > MAX_WALLS:
            raise ValueError(f"at most {MAX_WALLS} walls, got {len(walls)}")
        for k, w in enumerate(walls):
            if not isinstance(w, Wall):
                raise ValueError(f"wall {k} is a {type(w).__name__}, not a tcd.walls.Wall "
                                 "(make it with walls.plane / walls.cylinder, or Wall.from_dict)")
            self._check_fits(k, w)
            self._check_system(w)
        self._walls = WallList(walls)
        self._upload_walls(self.time)
        if hasattr(self, "contacts"):
            self._drop_wall_history()
        self._warn_wrong_side(walls)

    def _warn_wrong_side(self, walls) -> None:
        """RuntimeWarning for each wall with particle centres on its wrong side now."""
        if self.n == 0 or not walls:
            return
        x = get(self.particles.x, self.n).astype(float)
        system = get(self.particles.system, self.n)
        for k, w in enumerate(walls):
            mine = x if w.system < 0 else x[system == w.system]
            if not len(mine):
                continue
            d = mine - w.position(self.time)
            a = np.asarray(w.direction, float)
            s = d @ a
            if w.kind == "plane":
                wrong = s < 0.0
                where = "behind it (a plane holds particles on its normal's side)"
            else:
                radial = np.linalg.norm(d - np.outer(s, a), axis=1)
                wrong = (s >= w.extent[0]) & (s <= w.extent[1]) & (radial > w.radius)
                where = "outside it (a cylinder holds particles inside)"
            count = int(np.count_nonzero(wrong))
            if count:
                warnings.warn(f"wall {k} ({w.name!r}, {w.kind}): {count} particle centre(s) "
                              f"{where}; the contact law will push them through it",
                              RuntimeWarning, stacklevel=user_stacklevel())

    def _upload_walls(self, t: float) -> None:
        """All wall data (on set_walls); per step only `_move_walls` runs."""
        wf, walls = self.wall_fields, self.walls
        # one row copy (state.put_rows) for the eight fields: one kernel instance per wall
        # container instead of one per field
        put_fields(wf, {
            "kind": np.array([KINDS[w.kind] for w in walls], np.int32),
            "direction": np.array([w.direction for w in walls], float).reshape(-1, 3),
            "radius": np.array([w.radius for w in walls], float),
            "lo": np.array([w.extent[0] for w in walls], float),
            "hi": np.array([w.extent[1] for w in walls], float),
            "friction": np.array([w.friction for w in walls], float),
            "system": np.array([w.system for w in walls], np.int32),
            "rim": np.array([int(w.edges == "rim") for w in walls], np.int32)})
        wf.count[None] = len(walls)
        self._moving = any(w.motion != "fixed" for w in walls)
        self._move_walls(t, force=True)

    def _move_walls(self, t: float, force: bool = False) -> None:
        if not (force or self._moving):
            return
        h = self.settings.time_step
        put_fields(self.wall_fields, {
            "point": np.array([w.position(t) for w in self.walls], float).reshape(-1, 3),
            "velocity": np.array([w.step_velocity(t, h) for w in self.walls], float).reshape(-1, 3)})

    def _drop_wall_history(self):
        """Wall contacts start the next step from zero impulse: in the history the warm start
        reads, and in the current list that `state_dict` saves (which must hold the same)."""
        ct = self.contacts
        for j_field, r_fields, total in ((ct.prev_j, (ct.prev_impulse, ct.prev_old), ct.prev_total),
                                         (ct.j, (ct.impulse, ct.impulse_old), ct.total)):
            m = int(total[None])
            pj = get(j_field, m)
            for r_field in r_fields:
                pr = get(r_field, m)
                pr[pj >= self.n] = 0.0
                put(r_field, pr)

    # ---------------------------------------------------------------- the time step
    def step(self, count: int = 1) -> StepRecord:
        _integer("step count", count, 0, 2**62)
        for _ in range(count):
            self._step()
        return self.last

    def _bond_law_args(self) -> tuple:
        """The bond law's arguments of solver.bonds_prepare and bonds_finish."""
        law = self.bond_law
        mode = sk.MODE_PAPER if law.mode == "paper" else sk.MODE_BURGERS
        return (mode, law.maxwell_stiffness, law.maxwell_viscosity, law.kelvin_stiffness,
                law.kelvin_viscosity, law.tangent_factor)

    def _begin_step(self, warm_start: bool = False) -> bool:
        """The step up to its warm start: walls moved to the step's start, contacts built, the
        predictor, the bonds' and the contacts' terms of the step (benchmarks/ start from here to
        solve one step in their own ways), and with `warm_start` the warm start applied (the
        schedules that do not colour their items). One launch after the contacts' count
        (solver.step_begin). Returns whether the step holds bonds."""
        s = self.settings
        p, bd = self.particles, self.bonds
        self._move_walls(self.time)
        self._build_contacts(fill=False)
        has_bonds = bd.total[None] > 0
        sk.step_begin(p, self.wall_fields, self.neighbours, bd, self.contacts, self.alert,
                      s.time_step, self._reach_accel(), *s.gravity, s.theta,
                      self.time + s.time_step, *self._bond_law_args(),
                      s.warm_start_extrapolation, self.friction,
                      self.bond_law.friction_after_break, int(has_bonds),
                      int(has_bonds and s.bond_blocks), int(warm_start))
        return has_bonds

    def _step(self) -> None:
        s = self.settings
        h, theta = s.time_step, s.theta
        t_end = self.time + h
        p, wl, bd = self.particles, self.wall_fields, self.bonds
        coloured = self.schedule in COLOURED
        has_bonds = self._begin_step(warm_start=not coloured)
        ct = self.contacts
        if coloured:
            ncol, items = self._colour()
            self._by_colours(ncol, sk.warm_start_colours, p, ct, bd, self.colours)
        else:
            ncol, items = 0, 0
        if self.schedule == "serial":
            sk.nlgs_serial(p, wl, ct, bd, self.stats, s.max_sweeps, s.tolerance, s.check_every,
                           *self._sweep_flags())
            colours = 0
        elif self.schedule == "partitioned":
            self._solve_partitioned()
            colours = 0
        elif self.schedule == "resident":
            sk.solve_resident(p, wl, ct, bd, self.colours, self.stats, ncol, s.max_sweeps,
                              s.tolerance, s.check_every, self._resident_accel(),
                              self._blocks(), *self._resident_shape)
            colours = ncol
        else:
            colours = self._solve_coloured(ncol, items)
        slop = s.overlap_slop * 2.0 * self.r_min
        sk.step_end(p, wl, ct, bd, h, theta, t_end, *self._bond_law_args(),
                    self.bond_law.yield_stress, slop, 0 if coloured else s.projection_passes,
                    self.n, int(has_bonds))
        if s.projection_passes > 0 and coloured:
            for _ in range(s.projection_passes):
                self._by_colours(colours, sk.project_overlaps_colours, p, wl, ct, bd,
                                 self.colours, h, slop)
        if self._refit_contacts:
            self._refit_contacts = False
            need = capacity_class(int(1.5 * int(ct.total[None])) + 64)
            if need < ct.capacity:
                self._resize_contacts(need, keep_current=True)
        self.time = t_end
        self.step_index += 1
        self.last = StepRecord(self.time, int(self.stats.sweeps[None]), float(self.stats.residual[None]),
                               int(ct.total[None]), colours, self.bonds_intact_count())

    def _sweep_flags(self) -> tuple[int, int, int, int]:
        """The serial and partitioned sweeps' 0/1 kernel flags: symmetric order, NNCG, bond
        blocks, 'Quad ' convergence check."""
        s = self.settings
        return (int(s.sweep_order == "symmetric"), int(s.acceleration == "nncg"), self._blocks(),
                int(s.convergence == "quad"))

    def _solve_partitioned(self) -> None:
        s = self.settings
        p, wl, ct, bd = self.particles, self.wall_fields, self.contacts, self.bonds
        need = max(ct.capacity, bd.capacity, p.capacity)
        if self.partition is None or self.partition.capacity < need:
            release(self.partition)
            self.partition = acquire(Partition, need, p.capacity)
        symmetric, accel, blocks, quad = self._sweep_flags()
        pk.partition_items(p, ct, bd, self.partition, s.threads, blocks)
        pk.nlgs_partitioned(p, wl, ct, bd, self.stats, self.partition, s.threads, s.max_sweeps,
                            s.tolerance, s.check_every, symmetric, accel, blocks, quad)

    def _resident_accel(self) -> int:
        """solve_resident's `accel`: 0 plain, else the NNCG momentum (solver.resident_momentum)."""
        return self._resident_momentum if self.settings.acceleration == "nncg" else 0

    def _blocks(self) -> int:
        return 1 if self.settings.bond_blocks else 0

    def quad_norms(self) -> dict:
        """LMGC90's 'Quad ' convergence norms of the last step's impulses at the current
        velocities (all systems together; bonds and contacts as the step left them): QuadDV,
        QuadDVR, MeanDVoR and the largest of their absolute values, `residual`, which the step
        compared with the tolerance when `convergence = "quad"` (tcd/solver.py, quad_terms).
        Zeros when nothing carries an impulse."""
        sk.quad_norms(self.particles, self.wall_fields, self.contacts, self.bonds,
                      self.stats.quad)
        o = self.stats.quad.to_numpy()
        out = {"QuadDV": float(o[0]), "QuadDVR": float(o[1]), "MeanDVoR": float(o[2])}
        out["residual"] = max(abs(v) for v in out.values())
        return out

    def _by_colours(self, ncol: int, kernel, *args) -> None:
        """kernel(*args, base, blocks, k) for the colours 0 .. ncol - 1, k colours per call
        (_colours_per_launch, read at construction), colour after colour (the *_colours
        kernels of tcd/solver.py)."""
        k = self._per_launch
        for base in range(0, ncol, k):
            kernel(*args, base, self._blocks(), k)

    def _colour(self) -> tuple:
        """Colour this step's bond items and contacts (greedy or by rounds, see
        SolverSettings.colouring); (number of colours, number of items)."""
        s = self.settings
        ct, bd = self.contacts, self.bonds
        blocks = self._blocks()
        nb = self.n if blocks else int(bd.total[None])
        need = ct.capacity + (self.particles.capacity if blocks else bd.capacity)
        # grown when the items outgrow it, shrunk back to the items' class when it holds twice
        # that or more (a loaded bonded state's contact buffer is refitted after its first step:
        # the set sized then held 32768 slots for about 9300 items, 89.5 B per sphere of the
        # seed-1 shear in `change` alone; the colours do not depend on the capacity)
        bodies = self._resident_accel() == 2        # its per-particle scratch
        if (self.colours is None or self.colours.capacity < need
                or self.colours.capacity >= 2 * capacity_class(need)
                or self.colours.pool_args[2] != bodies):
            release(self.colours)
            self.colours = acquire(ColourSet, need, self.particles.capacity, self.systems, bodies)
        cs = self.colours
        rounds = s.colouring == "rounds" or (s.colouring == "auto" and _auto_arch() != "cpu")
        if rounds:
            sk.colour_rounds_init(self.n, ct, bd, cs, blocks)
            active = int(cs.active[None])
            ncol = 0
            while int(cs.coloured[None]) < active:
                if ncol == sk.MAX_COLOURS:
                    self.stats.colour_overflow[None] = 1
                    break
                sk.colour_round(self.n, ct, bd, cs, ncol, ncol * sk.COLOUR_PASSES, blocks)
                ncol += 1
            else:
                sk.colour_rounds_order(self.n, self.particles, ct, bd, cs, self.stats, ncol,
                                       blocks)
        else:
            sk.colour_greedy(self.n, self.particles, ct, bd, cs, self.stats, blocks)
        if self.stats.colour_overflow[None]:
            raise CapacityError("contact colouring needs more than "
                                f"{sk.MAX_COLOURS} colours (a body with that many contacts)")
        return int(self.stats.colours[None]), nb + int(ct.total[None])

    def _solve_coloured(self, ncol: int, items: int) -> int:
        s = self.settings
        p, wl, ct, bd = self.particles, self.wall_fields, self.contacts, self.bonds
        cs = self.colours
        sweeps, residual = 0, 0.0
        if self._base_in_field:
            k = self._per_launch
            calls = (ncol + k - 1) // k
            cs.ncol[None] = ncol
            cs.base[None] = 0
        while True:
            if self._base_in_field:
                for _ in range(calls):
                    sk.solve_colours_next(p, wl, ct, bd, cs, self._blocks(), k)
            else:
                self._by_colours(ncol, sk.solve_colours, p, wl, ct, bd, cs)
            sweeps += 1
            if sweeps % s.check_every == 0 or sweeps >= s.max_sweeps:
                if s.convergence == "quad":
                    residual = sk.quad_check_colours(p, wl, ct, bd, cs, items, self._blocks())
                else:
                    residual = sk.sweep_residual(cs, items)
                if residual <= s.tolerance or sweeps >= s.max_sweeps:
                    break
        self.stats.sweeps[None] = sweeps
        self.stats.residual[None] = residual
        # one convergence test over all systems: each system reports the common figures
        put_fields(self.stats, {"sys_sweeps": np.full(self.systems, sweeps, np.int32),
                                "sys_residual": np.full(self.systems, residual)})
        return ncol

    def _reach_accel(self) -> float:
        """The gravity's magnitude, for each grain's reach over a step (contacts.reach)."""
        return float(np.linalg.norm(self.settings.gravity))

    def _build_contacts(self, fill: bool = True) -> None:
        """The step's contact list from the neighbour list (a new one when it is stale):
        counted, scanned, the buffer grown if it overflows, then filled (`fill`; _begin_step
        fills it in solver.step_begin)."""
        p, wl, bd = self.particles, self.wall_fields, self.bonds
        h, a = self.settings.time_step, self._reach_accel()
        if not self._neighbours_valid or ck.neighbour_list_stale(p, self.neighbours, h, a):
            self._build_neighbours()
        while True:
            ct = self.contacts
            total = ck.contact_count(p, wl, self.neighbours, bd, ct, self.alert, h, a, self.n)
            if total <= ct.capacity:
                break
            self._resize_contacts(int(total * 1.5) + 16)
        ct.total[None] = total
        if fill:
            ck.contact_fill(p, wl, self.neighbours, bd, ct, self.alert, h, a)

    def _build_neighbours(self) -> None:
        """A new neighbour list (contacts.neighbour_pass): the grid walked with each particle's
        box enlarged by half the alert distance plus its margin."""
        p = self.particles
        h, a = self.settings.time_step, self._reach_accel()
        half_alert = 0.5 * self.alert
        ck.neighbour_margins(p, self.neighbours, self._half_skin, h, a)
        while True:
            g = self.grid
            total = ck.grid_count(p, g, self.neighbours, half_alert)
            if total <= g.capacity:
                break
            # a quarter more than needed (the capacity classes add up to another quarter):
            # the incidence list is the largest broad-phase buffer, and stays allocated
            capacity = int(1.25 * total) + 64
            self.grow_events.append(f"grid items {g.capacity} -> {capacity}")
            release(g)
            self.grid = self._make_grid(capacity)
        ck.grid_scatter(p, self.grid, self.neighbours, half_alert)
        while True:
            nb = self.neighbours
            total = ck.neighbour_count(p, self.grid, nb, half_alert, self.n)
            if total <= nb.capacity:
                break
            capacity = int(total * 1.5) + 16
            self.grow_events.append(f"neighbour pairs {nb.capacity} -> {capacity}")
            release(nb)
            self.neighbours = acquire(Neighbours, capacity, p.capacity)
            ck.neighbour_margins(p, self.neighbours, self._half_skin, h, a)
        nb.total[None] = total
        ck.neighbour_pass(p, self.grid, nb, half_alert)
        self._neighbours_valid = True
        self.neighbour_builds += 1

    def _resize_contacts(self, capacity: int, keep_current: bool = False) -> None:
        """A contact buffer of `capacity` slots holding the warm-start history of the old one
        and, with `keep_current`, its current contact list too (between steps)."""
        old = self.contacts
        self.grow_events.append(f"contacts {old.capacity} -> {capacity}")
        new = acquire(Contacts, capacity, self.particles.capacity)
        m = int(old.prev_total[None])
        put_fields(new, get_fields(old, ("prev_j", "prev_impulse", "prev_old"), m))
        new.prev_start.from_numpy(old.prev_start.to_numpy())
        new.prev_total[None] = m
        if keep_current:
            k = int(old.total[None])
            put_fields(new, get_fields(old, ("i", "j", "normal", "impulse", "impulse_old", "rhs",
                                             "wnn", "wtt", "mu", "colour", "gap"), k))
            new.count.from_numpy(old.count.to_numpy())
            new.start.from_numpy(old.start.to_numpy())
            new.total[None] = k
        release(old)
        self.contacts = new

    # ---------------------------------------------------------------- bonds
    def create_bonds(self, gap_tolerance: float) -> int:
        """Bond every particle pair whose gap is below `gap_tolerance` (m), stress-free, at the
        current time. Existing bonds are replaced. Walls are never bonded. Returns the count."""
        _finite("bond gap tolerance", gap_tolerance, low=0.0)
        x, r = self.positions(), self.radii()
        pairs = self._candidate_pairs(gap_tolerance)
        if len(pairs):
            gaps = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1) - r[pairs[:, 0]] - r[pairs[:, 1]]
            keep = gaps < gap_tolerance
            pairs, gaps = pairs[keep], gaps[keep]
        else:
            gaps = np.zeros(0)
        b = len(pairs)
        self._set_bond_arrays({
            "i": pairs[:, 0].astype(np.int32), "j": pairs[:, 1].astype(np.int32),
            "g0": gaps, "created": np.full(b, self.time),
            "area": math.pi * np.minimum(r[pairs[:, 0]], r[pairs[:, 1]]) ** 2 if b else np.zeros(0),
        })
        return b

    def _candidate_pairs(self, reach: float) -> np.ndarray:
        """All particle pairs with gap < reach, sorted (i < j), via the grid kernels (in a
        contact buffer of their own: the simulation's contacts and their history stay as they
        are, so that `state_dict` still gives the state the next step starts from)."""
        saved_alert = self.alert
        saved_bonds = self.bonds
        saved_contacts = self.contacts
        self.contacts = acquire(Contacts, saved_contacts.capacity, self.particles.capacity)
        self.bonds = self._bond_buffer(0)
        self.alert = max(reach, 1e-300)
        saved_count = self.wall_fields.count[None]
        self.wall_fields.count[None] = 0
        # a list built for the contacts' alert distance need not hold every pair within
        # `reach` (a larger range, and margins partly used since the list was built): a new
        # one for it, and a new one again at the next step (any list gives the same numbers)
        self._neighbours_valid = False
        try:
            self._build_contacts()
            m = int(self.contacts.total[None])
            pairs = np.stack([get(self.contacts.i, m), get(self.contacts.j, m)], axis=1)
        finally:
            self.alert = saved_alert
            self._neighbours_valid = False
            release(self.bonds)
            self.bonds = saved_bonds
            release(self.contacts)
            self.contacts = saved_contacts
            self.wall_fields.count[None] = saved_count
        return pairs.reshape(-1, 2)

    _BOND_DEFAULTS = {"i": 0, "j": 0, "state": 0, "g0": 0.0, "created": 0.0, "area": 0.0,
                      "hd_n": 0.0, "hk_n": 0.0, "impulse": 0.0, "d_t": 0.0, "hd_t": 0.0,
                      "hk_t": 0.0, "broken_time": np.nan, "broken_pos": np.nan, "impulse_prev": 0.0}
    _BOND_VECTORS = ("impulse", "d_t", "hd_t", "hk_t", "broken_pos", "impulse_prev")

    def _bond_buffer(self, b: int) -> Bonds:
        """A bond buffer for `b` bonds from the pool. Without bonds, the smallest buffer: 64
        slots, below state.MIN_SLOTS (one class for every size already, and a 2600-sphere
        pour would otherwise hold 150 B per particle more)."""
        return acquire(Bonds, max(b, 1), self.particles.capacity,
                       b > 0 and self.settings.bond_blocks,
                       b > 0 and self.settings.bond_frame == "end", minimum=None if b else 64)

    def _set_bond_arrays(self, a: dict) -> None:
        """Install a bond set given as arrays (missing state arrays take their defaults)."""
        b = len(a["i"])
        # bonded pairs leave the contact list: after the next step its buffer (sized for an
        # unbonded sample, or for a batch's histories) is refitted to what the step needed
        self._refit_contacts = b > 0
        release(self.bonds)
        bd = self._bond_buffer(b)
        order = np.lexsort((a["j"], a["i"])) if b else np.zeros(0, int)
        values = {}
        for key, default in self._BOND_DEFAULTS.items():
            shape = (b, 3) if key in self._BOND_VECTORS else (b,)
            arr = np.asarray(a[key]) if key in a else np.full(shape, default)
            values[key] = arr[order].reshape(shape)
        put_fields(bd, values)
        start = np.zeros(self.n + 1, np.int32)
        np.add.at(start, np.asarray(a["i"], int)[order] + 1, 1)
        put(bd.start, np.cumsum(start))
        js = np.asarray(a["j"], int)[order]
        rev = np.argsort(js, kind="stable").astype(np.int32)       # bond indices, by j then i
        rev_start = np.zeros(self.n + 1, np.int32)
        np.add.at(rev_start, js + 1, 1)
        put(bd.rev, rev)
        put(bd.rev_start, np.cumsum(rev_start))
        bd.total[None] = b
        bd.broken[None] = int(np.count_nonzero(np.asarray(a.get("state", np.zeros(b))) != sk.INTACT))
        self.bonds = bd

    def bonds_intact_count(self) -> int:
        return int(self.bonds.total[None]) - int(self.bonds.broken[None])

    # ---------------------------------------------------------------- particle numbering
    def _system_ids(self) -> np.ndarray:
        """Each particle's system, from the host's system_start (no read of the field)."""
        return np.repeat(np.arange(self.systems), np.diff(self.system_start))

    def _identity_index(self) -> np.ndarray:
        """Each particle's index within its own system: the sample_index of a simulation whose
        particles were never renumbered."""
        return (np.arange(self.n) - self.system_start[self._system_ids()]).astype(np.int32)

    def _set_sample_index(self, index) -> None:
        self.sample_index = self._checked_sample_index(index)

    def _checked_sample_index(self, index) -> np.ndarray:
        index = np.asarray(index).reshape(-1)
        if index.shape != (self.n,) or not np.issubdtype(index.dtype, np.integer):
            raise ValueError(f"sample_index must be {self.n} integers, got shape {index.shape}, "
                             f"dtype {index.dtype}")
        for s in range(self.systems):
            _check_permutation(f"sample_index of system {s}",
                               index[self.system_start[s]:self.system_start[s + 1]])
        return index.astype(np.int32)

    @property
    def sweep_order_used(self) -> str:
        """The sweep order the schedule runs: settings.sweep_order on the serial and partitioned
        schedules; the coloured and resident ones sweep their colours forward."""
        return "forward" if self.schedule in COLOURED else self.settings.sweep_order

    @property
    def acceleration_used(self) -> str:
        """settings.acceleration, except on the coloured schedule, which is always plain."""
        return "none" if self.schedule == "coloured" else self.settings.acceleration

    @property
    def resident_block(self) -> dict:
        """The resident schedule's launch: threads per system (1 on the CPU) and its NNCG
        momentum ("bodies", "items" or "none"; solver.resident_momentum); {} on the others."""
        if self.schedule != "resident":
            return {}
        names = {accel: name for name, accel in sk.RESIDENT_MOMENTUM.items()}
        return {"threads": self._resident_shape[0],
                "momentum": names.get(self._resident_accel(), "none")}

    @property
    def renumbered(self) -> bool:
        """True when some particle's index differs from its sample_index."""
        return not np.array_equal(self.sample_index, self._identity_index())

    def renumber(self, order) -> "Simulation":
        """A new simulation holding this one's state with the particles renumbered: new
        particle k is old particle order[k] (its contacts, their impulse histories and the
        walls' forces follow it; contacts are listed again in canonical order). Each particle
        keeps the index it had in the sample as `sample_index` (state files:
        particles/sample_index), so that a renumbered run can be traced back to its sample.

        Why: the Gauss-Seidel reads each body's neighbours; numbered along an axis, neighbours
        lie close in memory, and the partitioned schedule's slabs (cut across that axis) own
        contiguous ranges of particles, so its threads do not write the same cache lines.
        The visiting order changes, so the numbers change at the level of the solver's
        tolerance. One system only, before bonds are created (bond records are directed
        from i to j). This simulation is left as it was; close it when done."""
        if self.systems > 1:
            raise ValueError("renumber works on one system; renumber each before batching")
        if int(self.bonds.total[None]) > 0:
            raise ValueError("renumber before creating bonds (this simulation has "
                             f"{int(self.bonds.total[None])})")
        n = self.n
        order = np.asarray(order).reshape(-1)
        if not np.issubdtype(order.dtype, np.integer) or order.shape != (n,):
            raise ValueError(f"order must be a permutation of 0..{n - 1}")
        _check_permutation("order", order)
        d = self.state_dict()
        new_of = np.empty(n, np.int64)
        new_of[order] = np.arange(n)
        e = {k: v[order] for k, v in d.items() if k.startswith("particles/")}
        e["particles/sample_index"] = self.sample_index[order].copy()
        ci = new_of[d["contacts/i"]]
        cj = d["contacts/j"].astype(np.int64)
        body = cj < n
        cj = np.where(body, new_of[np.minimum(cj, n - 1)], cj)
        # a contact is listed under its lower particle, its impulse acting on the other one
        swap = body & (cj < ci)
        first, second = np.where(swap, cj, ci), np.where(swap, ci, cj)
        sign = np.where(swap, -1.0, 1.0)[:, None]
        o = np.lexsort((second, first))
        e["contacts/i"] = first[o].astype(np.int32)
        e["contacts/j"] = second[o].astype(np.int32)
        for key in ("impulse", "impulse_old"):
            e["contacts/" + key] = (d["contacts/" + key] * sign)[o].astype(d["contacts/" + key].dtype)
        e["contacts/gap"] = d["contacts/gap"][o]
        e["contacts/start"] = np.searchsorted(e["contacts/i"], np.arange(n + 1)).astype(np.int32)
        for k, v in d.items():
            if k.startswith(("walls/", "bonds/")):
                e[k] = v
        # (masses, inertias, sample_index and the state come with load_state_dict)
        new = type(self)(e["particles/radius"], e["particles/x"], walls=self.walls,
                         density=self.density, layer=e["particles/layer"],
                         friction=self.friction, settings=self.settings, bond_law=self.bond_law,
                         domain=self.domain, cell_size=self.cell_size, time=self.time,
                         contact_capacity=self.contacts.capacity)
        new.load_state_dict(e)
        new.step_index = self.step_index
        return new

    # ---------------------------------------------------------------- state in / out
    def state_dict(self) -> dict:
        """The grains, contact and bond histories and last wall forces, as NumPy arrays (HDF5
        layout): with the simulation's time, walls and settings (not in it), everything needed
        to continue the run bit-exactly (`load_state_dict`). With `bond_frame = "end"` also
        bonds/turn, the frame turn's central impulse on j over the last step: the bond's whole
        impulse is bonds/impulse (its own, the next step's warm start) plus bonds/turn."""
        p, ct, bd, wf = self.particles, self.contacts, self.bonds, self.wall_fields
        n, m, b, nw = self.n, int(ct.total[None]), int(bd.total[None]), len(self.walls)
        d = {"particles/" + k: v for k, v in get_fields(p, PARTICLE_STATE, n).items()}
        if self.systems > 1:
            d["particles/system"] = get(p.system, n)
        if self.renumbered:
            d["particles/sample_index"] = self.sample_index.copy()
        d.update({"contacts/" + k: v for k, v in
                  get_fields(ct, ("i", "j", "impulse", "gap", "impulse_old"), m).items()})
        d.update({
            "contacts/start": get(ct.start, n + 1),
            "walls/kind": np.array([KINDS[w.kind] for w in self.walls], np.int32),
            "walls/point": np.array([w.position(self.time) for w in self.walls]).reshape(nw, 3),
            "walls/direction": np.array([w.direction for w in self.walls], float).reshape(nw, 3),
            "walls/radius": np.array([w.radius for w in self.walls], float),
            "walls/extent": np.array([w.extent for w in self.walls], float).reshape(nw, 2),
            "walls/force": get(wf.force, nw),
        })
        d.update({"bonds/" + k: v for k, v in get_fields(bd, self._BOND_DEFAULTS, b).items()})
        d["bonds/state"] = d["bonds/state"].astype(np.int8)
        if bd.has_turn:
            # the turn's central impulse on j over the last step (bond_frame = "end"); reset
            # every step, so not needed to continue the run: the states files' frames add it
            # to bonds/impulse (runner.frame_of), the whole impulse the bond gave
            d["bonds/turn"] = get(bd.turn, b)
        return d

    def load_state_dict(self, d: dict) -> None:
        """Restore particles, contact history and bonds written by `state_dict` (bit-exact).
        Walls are part of the scenario: set them with `set_walls`."""
        p = self.particles
        if not isinstance(d, dict):
            raise TypeError(f"load_state_dict takes a state_dict (a dict of arrays), got a "
                            f"{type(d).__name__}")
        missing = [k for k in STATE_KEYS if k not in d]
        if missing:
            raise ValueError(f"state lacks {', '.join(missing)} (not a state_dict of a Simulation)")
        n = len(d["particles/radius"])
        if n != self.n:
            raise ValueError(f"state has {n} particles, simulation has {self.n}")
        system = np.asarray(d.get("particles/system", np.zeros(n, np.int32)))
        if not np.array_equal(system, get(p.system, n)):
            raise ValueError("state's particle systems differ from the simulation's "
                             "(build the simulation with system=...)")
        check_state_arrays(d)
        radius = np.asarray(d["particles/radius"]).astype(backend.numpy_real())
        if not np.array_equal(radius, get(p.radius, n)):
            # the grid cell, alert distance and projection slop follow the radii
            raise ValueError("state's particle radii differ from the simulation's (a state of "
                             "another sample): build the Simulation with the state's radii")
        # every check before the first write: a refused state leaves the simulation as it was
        sample_index = self._checked_sample_index(d.get("particles/sample_index",
                                                        self._identity_index()))
        put_fields(p, {key: d["particles/" + key] for key in PARTICLE_STATE})
        self._inverse_masses = None
        self.sample_index = sample_index
        self._neighbours_valid = False
        m = len(d["contacts/i"])
        if m > self.contacts.capacity:
            self._resize_contacts(m)
        ct = self.contacts
        if m == 0:      # (a file written before session 47 may hold a pooled buffer's old table)
            d = {**d, "contacts/start": np.zeros(self.n + 1, np.int32)}
        # each contact's impulse the step before (a state written before the extrapolated warm
        # start lacks it: the last impulse then, which extrapolates nothing at the next step);
        # and the current contact list too, so that state_dict(load_state_dict(d)) == d even in
        # a pooled container that held another simulation's contacts
        old = d.get("contacts/impulse_old", d["contacts/impulse"])
        put_fields(ct, {"prev_j": d["contacts/j"], "prev_impulse": d["contacts/impulse"],
                        "prev_old": old, "i": d["contacts/i"], "j": d["contacts/j"],
                        "impulse": d["contacts/impulse"], "gap": d["contacts/gap"],
                        "impulse_old": old})
        put_fields(ct, {"prev_start": d["contacts/start"], "start": d["contacts/start"]})
        ct.prev_total[None] = m
        ct.total[None] = m
        bonds = {k.split("/", 1)[1]: np.asarray(v) for k, v in d.items() if k.startswith("bonds/")}
        bonds["state"] = bonds["state"].astype(np.int32)
        # likewise each bond's impulse the step before
        if "impulse" in bonds:
            bonds.setdefault("impulse_prev", bonds["impulse"])
        self._set_bond_arrays(bonds)
        # the wall forces of the last step: a servo plate reads them before the next step
        force = np.asarray(d.get("walls/force", np.zeros((0, 3))), float).reshape(-1, 3)
        if len(force) == len(self.walls):
            put(self.wall_fields.force, force)

    # ---------------------------------------------------------------- batched systems
    @classmethod
    def batch(cls, sims: Sequence["Simulation"]) -> "Simulation":
        """One simulation holding the independent simulations `sims` side by side in the same
        fields: sims[s] becomes system s (its particles, contact history, bonds and walls, the
        walls tagged with s), all in their own coordinates (systems may overlap in space: they
        never interact). One step then advances every system; on the CPU the serial
        Gauss-Seidel runs one system per core, each to its own convergence.

        The systems must share the clock, solver settings, bond law and material. The alert
        distance and the projection slop are those of the smallest grain of all systems; a
        larger alert only adds pairs that carry no impulse, so each system steps as it would
        alone (bit for bit when the smallest radii agree, which tests/test_batch.py checks).
        `split` gives the systems back."""
        sims = list(sims)
        if not sims:
            raise ValueError("batch needs at least one simulation")
        for k, o in enumerate(sims):
            if not isinstance(o, Simulation):
                raise TypeError(f"batch takes Simulations; item {k} is a {type(o).__name__}")
        ref = sims[0]
        for k, o in enumerate(sims):
            if o.systems != 1:
                raise ValueError(f"simulation {k} is already a batch of {o.systems} systems")
            for attr in ("time", "settings", "bond_law", "friction", "density"):
                mine, theirs = getattr(o, attr), getattr(ref, attr)
                if mine != theirs:
                    if dataclasses.is_dataclass(mine) and type(mine) is type(theirs):
                        fields = [f"{f.name} {getattr(mine, f.name)!r} != "
                                  f"{getattr(theirs, f.name)!r}"
                                  for f in dataclasses.fields(mine)
                                  if getattr(mine, f.name) != getattr(theirs, f.name)]
                        raise ValueError(f"simulation {k} differs from simulation 0 in {attr}: "
                                         + ", ".join(fields))
                    raise ValueError(f"simulation {k} differs from simulation 0 in {attr}: "
                                     f"{mine!r} != {theirs!r}")
        states = [o.state_dict() for o in sims]
        n_tot = sum(o.n for o in sims)
        wall_list, parts = [], {}
        contacts = {"i": [], "j": [], "impulse": [], "impulse_old": [], "gap": [], "start": []}
        bonds: dict = {}
        p_off = w_off = c_off = 0
        for k, (o, d) in enumerate(zip(sims, states)):
            for key in ("x", "v", "w", "radius", "layer", "inv_mass", "inv_inertia", "f_ext"):
                parts.setdefault(key, []).append(d["particles/" + key])
            parts.setdefault("system", []).append(np.full(o.n, k, np.int32))
            parts.setdefault("sample_index", []).append(o.sample_index)
            j = d["contacts/j"]
            contacts["i"].append(d["contacts/i"] + p_off)
            contacts["j"].append(np.where(j < o.n, j + p_off, n_tot + w_off + (j - o.n)).astype(np.int32))
            contacts["impulse"].append(d["contacts/impulse"])
            contacts["impulse_old"].append(d["contacts/impulse_old"])
            contacts["gap"].append(d["contacts/gap"])
            contacts["start"].append(d["contacts/start"][:-1] + c_off)
            for key in cls._BOND_DEFAULTS:
                v = d["bonds/" + key]
                bonds.setdefault(key, []).append(v + p_off if key in ("i", "j") else v)
            wall_list += [dataclasses.replace(w, system=k) for w in o.walls]
            p_off += o.n
            w_off += len(o.walls)
            c_off += len(d["contacts/i"])
        contacts["start"].append(np.array([c_off], np.int32))
        merged = {"particles/" + k: np.concatenate(v) for k, v in parts.items()}
        merged.update({"contacts/" + k: np.concatenate(v) for k, v in contacts.items()})
        merged.update({"bonds/" + k: np.concatenate(v) for k, v in bonds.items()})
        merged["walls/force"] = np.concatenate([d["walls/force"] for d in states]).reshape(-1, 3)
        lo = np.min([o.domain[0] for o in sims], axis=0)
        hi = np.max([o.domain[1] for o in sims], axis=0)
        batch = cls(merged["particles/radius"], merged["particles/x"], walls=wall_list,
                    density=ref.density, layer=merged["particles/layer"], friction=ref.friction,
                    settings=ref.settings, bond_law=ref.bond_law, domain=(lo, hi),
                    cell_size=min(o.cell_size for o in sims), time=ref.time,
                    system=merged["particles/system"],
                    contact_capacity=max(64, int(1.25 * c_off) + 64))
        batch.load_state_dict(merged)
        batch.step_index = ref.step_index
        return batch

    def system_slice(self, s: int) -> slice:
        """The particles of system s."""
        if isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)):
            raise TypeError(f"a system is named by its integer index, got {s!r}")
        if not 0 <= s < self.systems:
            raise ValueError(f"no system {s} (the simulation has {self.systems})")
        return slice(int(self.system_start[s]), int(self.system_start[s + 1]))

    def system_walls(self, s: int) -> list[int]:
        """Indices of the walls that act on system s (its own and the untagged ones)."""
        self.system_slice(s)
        return [k for k, w in enumerate(self.walls) if w.system in (-1, s)]

    def system_stats(self) -> tuple[np.ndarray, np.ndarray]:
        """Sweeps and residual of the last step, per system."""
        return get(self.stats.sys_sweeps, self.systems), get(self.stats.sys_residual, self.systems).astype(float)

    def split(self, systems=None) -> list[dict]:
        """The state of each system (or of those listed in `systems`) as `state_dict` would
        give it for that system alone (particle and wall indices of its own), with its walls
        (untagged) under "walls"."""
        d = self.state_dict()
        out = []
        ci, cj = d["contacts/i"], d["contacts/j"]
        bi = d["bonds/i"]
        if any(w.system == -1 for w in self.walls):
            raise ValueError("split needs every wall tagged with its system")
        for s in (range(self.systems) if systems is None else systems):
            sl = self.system_slice(s)
            n_s = sl.stop - sl.start
            wk = [k for k, w in enumerate(self.walls) if w.system == s]
            c0, c1 = int(d["contacts/start"][sl.start]), int(d["contacts/start"][sl.stop])
            j = cj[c0:c1]
            wall_pos = np.full(max(len(self.walls), 1), -1, np.int64)
            wall_pos[wk] = np.arange(len(wk))
            e = {"particles/" + k: d["particles/" + k][sl]
                 for k in ("x", "v", "w", "radius", "layer", "inv_mass", "inv_inertia", "f_ext")}
            if not np.array_equal(self.sample_index[sl], np.arange(n_s)):
                e["particles/sample_index"] = self.sample_index[sl].copy()
            e["contacts/i"] = ci[c0:c1] - sl.start
            e["contacts/j"] = np.where(j < self.n, j - sl.start,
                                       n_s + wall_pos[np.maximum(j - self.n, 0)]).astype(j.dtype)
            e["contacts/impulse"] = d["contacts/impulse"][c0:c1]
            e["contacts/impulse_old"] = d["contacts/impulse_old"][c0:c1]
            e["contacts/gap"] = d["contacts/gap"][c0:c1]
            e["contacts/start"] = d["contacts/start"][sl.start:sl.stop + 1] - c0
            keep = (bi >= sl.start) & (bi < sl.stop)
            for key in (*self._BOND_DEFAULTS, *(["turn"] if "bonds/turn" in d else [])):
                v = d["bonds/" + key][keep]
                e["bonds/" + key] = v - sl.start if key in ("i", "j") else v
            for key in ("kind", "point", "direction", "radius", "extent", "force"):
                e["walls/" + key] = d["walls/" + key][wk]
            e["walls"] = [dataclasses.replace(self.walls[k], system=-1) for k in wk]
            out.append(e)
        return out

    def memory_bytes(self) -> int:
        parts = [self.particles, self.contacts, self.bonds, self.grid, self.neighbours,
                 self.wall_fields]
        parts += [o for o in (self.colours, self.partition) if o is not None]
        return sum(field_bytes(o) for o in parts)

    # ---------------------------------------------------------------- convenience readers
    def positions(self) -> np.ndarray:
        return get(self.particles.x, self.n).astype(float)

    def velocities(self) -> np.ndarray:
        return get(self.particles.v, self.n).astype(float)

    def angular_velocities(self) -> np.ndarray:
        return get(self.particles.w, self.n).astype(float)

    def radii(self) -> np.ndarray:
        return get(self.particles.radius, self.n).astype(float)

    def _wall_index(self, k) -> int:
        """`k` as the index of one of the walls; ValueError naming it otherwise (a float, a
        bool, or out of range: Taichi read past the walls' force field)."""
        if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) \
                or not 0 <= k < len(self.walls):
            raise ValueError(f"no wall {k!r}: the simulation has {len(self.walls)} walls "
                             f"(0 to {len(self.walls) - 1})")
        return int(k)

    def wall_force(self, k: int) -> np.ndarray:
        """Force (N) the grains exerted on wall k over the last step."""
        return self.wall_fields.force[self._wall_index(k)].to_numpy().astype(float)

    def set_external_force(self, force) -> None:
        """Force (N) on every particle: one 3-vector per particle, or one for all."""
        put(self.particles.f_ext, per_particle("external force", force, self.n))

    def set_positions(self, x) -> None:
        x = per_particle("positions", x, self.n, broadcast=False)
        # as the constructor: two grains of one system at one centre have no contact normal
        _check_distinct_centres(np.asarray(x, float), self._system_ids())
        put(self.particles.x, x)
        self._neighbours_valid = False

    def set_velocities(self, v) -> None:
        """Velocities (m/s): one 3-vector per particle, or one for all."""
        put(self.particles.v, per_particle("velocities", v, self.n))

    def contact_arrays(self) -> dict:
        ct = self.contacts
        m = int(ct.total[None])
        c = get_fields(ct, ("i", "j", "impulse", "normal", "gap"), m)
        return {"i": c["i"], "j": c["j"], "impulse": c["impulse"].astype(float),
                "normal": c["normal"].astype(float), "gap": c["gap"].astype(float)}

    def set_angular_velocities(self, w) -> None:
        put(self.particles.w, per_particle("angular velocities", w, self.n))

    def bonds_state_counts(self) -> tuple:
        """(intact, broken in tension, broken in shear)."""
        b = int(self.bonds.total[None])
        if b == 0:
            return 0, 0, 0
        s = get(self.bonds.state, b)
        return (int(np.count_nonzero(s == sk.INTACT)), int(np.count_nonzero(s == sk.BROKEN_TENSION)),
                int(np.count_nonzero(s == sk.BROKEN_SHEAR)))

    def inverse_masses(self) -> tuple[np.ndarray, np.ndarray]:
        """(inverse masses, inverse moments of inertia), one per particle: 0 for a kinematic
        (fixed) one. Those of the state last loaded, which may differ from `density`'s. Read
        once and kept (they change only when a state is loaded)."""
        if self._inverse_masses is None:
            p = self.particles
            self._inverse_masses = (get(p.inv_mass, self.n).astype(float),
                                    get(p.inv_inertia, self.n).astype(float))
        return self._inverse_masses

    def kinetic_energy(self) -> float:
        """Kinetic energy (J) of the free particles, from their own masses (a kinematic one
        has infinite mass: it carries none)."""
        from .observables import kinetic_energy_of
        return kinetic_energy_of(self.velocities(), self.angular_velocities(), *self.inverse_masses())

    def replace_wall(self, k: int, wall: Wall) -> None:
        """Replace wall k keeping its contact history (e.g. a servo-controlled plate)."""
        k = self._wall_index(k)
        if not isinstance(wall, Wall):
            raise ValueError(f"wall {k}: a {type(wall).__name__}, not a tcd.walls.Wall")
        self._check_fits(k, wall)
        self._check_system(wall)
        self._walls = WallList(self._walls[:k] + [wall] + self._walls[k + 1:])
        self._upload_walls(self.time)

    def _check_system(self, w: Wall) -> None:
        """Refuse (before anything changes) a wall tagged with a system the simulation lacks."""
        if w.system >= self.systems:
            raise ValueError(f"wall {w.name!r} is tagged with system {w.system}, but the "
                             f"simulation has {self.systems} system(s)")

    def _check_fits(self, k: int, w: Wall) -> None:
        """A cylinder (its inner surface holds the spheres) must be wider than the largest
        sphere of its system, or no sphere fits inside it."""
        if w.kind != "cylinder" or self.n == 0:
            return
        r = get(self.particles.radius, self.n)
        if 0 <= w.system < self.systems:
            r = r[self.system_start[w.system]:self.system_start[w.system + 1]]
        if len(r) and float(r.max()) >= w.radius:
            raise ValueError(f"wall {k} ({w.name or 'cylinder'}): its radius {w.radius:g} m is not "
                             f"larger than the largest sphere radius {float(r.max()):g} m: no "
                             "sphere fits inside it")


class BatchReads:
    """A batch's arrays read once per step for all its SystemViews: on a GPU each read waits for
    the device and copies a whole field, so five views each reading each field (positions,
    velocities, bond states, ...) would make five copies of each; shared, a recorded step of
    `tcd run --batch` reads 9 arrays for all the systems. Keyed on the batch's step: the views
    read between steps, and the batch steps."""

    def __init__(self, batch: Simulation):
        self.batch = batch
        self._step, self._arrays = None, {}
        self.reads = 0          # whole-batch reads made (a count for tests)

    def __call__(self, key: str, read):
        if self._step != self.batch.step_index:
            self._step, self._arrays = self.batch.step_index, {}
        if key not in self._arrays:
            self._arrays[key] = read()
            self.reads += 1
        return self._arrays[key]


class SystemView:
    """System s of a batch seen through the part of the Simulation interface that the protocols
    and the runner read (clock, walls and their forces, particles, bonds, state): the numbers of
    that system alone, with its own particle and wall indices. Reads only; the batch steps.
    Views made by `SystemView.all` share one BatchReads: each field is read once per step for
    all of them, and each view takes its slice (a copy: a caller may change it)."""

    def __init__(self, batch: Simulation, s: int, reads: BatchReads | None = None):
        self.batch, self.s = batch, s
        self.slice = batch.system_slice(s)
        self.n = self.slice.stop - self.slice.start
        self.wall_index = [k for k, w in enumerate(batch.walls) if w.system == s]
        self._split, self._split_step = None, None
        self.reads = BatchReads(batch) if reads is None else reads

    @classmethod
    def all(cls, batch: Simulation) -> list:
        """A view of each system of the batch, sharing one BatchReads."""
        reads = BatchReads(batch)
        return [cls(batch, s, reads) for s in range(batch.systems)]

    time = property(lambda self: self.batch.time)
    step_index = property(lambda self: self.batch.step_index)
    settings = property(lambda self: self.batch.settings)
    bond_law = property(lambda self: self.batch.bond_law)
    density = property(lambda self: self.batch.density)
    domain = property(lambda self: self.batch.domain)

    @property
    def walls(self) -> list:
        return [dataclasses.replace(self.batch.walls[k], system=-1) for k in self.wall_index]

    def positions(self):
        return self.reads("x", self.batch.positions)[self.slice].copy()

    def velocities(self):
        return self.reads("v", self.batch.velocities)[self.slice].copy()

    def angular_velocities(self):
        return self.reads("w", self.batch.angular_velocities)[self.slice].copy()

    def radii(self):
        return self.reads("radius", self.batch.radii)[self.slice].copy()

    def inverse_masses(self) -> tuple[np.ndarray, np.ndarray]:
        inv_mass, inv_inertia = self.batch.inverse_masses()
        return inv_mass[self.slice].copy(), inv_inertia[self.slice].copy()

    def wall_force(self, k: int) -> np.ndarray:
        force = self.reads("wall_force",
                           lambda: self.batch.wall_fields.force.to_numpy().astype(float))
        return force[self.wall_index[k]].copy()

    def _bond_range(self) -> tuple[int, int]:
        start = self.reads("bond_start", self.batch.bonds.start.to_numpy)
        return int(start[self.slice.start]), int(start[self.slice.stop])

    def bonds_state_counts(self) -> tuple:
        b0, b1 = self._bond_range()
        bd = self.batch.bonds
        s = self.reads("bond_state", lambda: get(bd.state, int(bd.total[None])))[b0:b1]
        return (int(np.count_nonzero(s == sk.INTACT)), int(np.count_nonzero(s == sk.BROKEN_TENSION)),
                int(np.count_nonzero(s == sk.BROKEN_SHEAR)))

    def bonds_intact_count(self) -> int:
        return self.bonds_state_counts()[0]

    def contact_count(self) -> int:
        start = self.reads("contact_start", self.batch.contacts.start.to_numpy)
        return int(start[self.slice.stop]) - int(start[self.slice.start])

    def solver_stats(self) -> tuple[int, float]:
        sweeps, residual = self.reads("solver_stats", self.batch.system_stats)
        return int(sweeps[self.s]), float(residual[self.s])

    def kinetic_energy(self) -> float:
        from .observables import kinetic_energy_of
        inv_mass, inv_inertia = self.batch.inverse_masses()
        return kinetic_energy_of(self.velocities(), self.angular_velocities(),
                                 inv_mass[self.slice], inv_inertia[self.slice])

    def state_dict(self) -> dict:
        """The system's state as `Simulation.state_dict` of it alone (split of the batch, kept
        until the batch steps again)."""
        if self._split_step != self.batch.step_index:
            d = dict(self.batch.split([self.s])[0])
            d.pop("walls")
            self._split, self._split_step = d, self.batch.step_index
        return self._split


def check_state_arrays(d: dict) -> None:
    """Refuse, naming the key, a state (the keys of `Simulation.state_dict`, at least
    STATE_KEYS) whose arrays would corrupt the run once installed: wrong lengths (they were
    zero-padded or cut), indices out of range, NaN or infinite numbers, negative inverse
    masses, bond states other than intact or broken. `Simulation.load_state_dict` asks it,
    and `runner.read_prepared` of a sample before any simulation is built."""
    n = len(d["particles/radius"])
    for key in ("x", "v", "w"):
        per_particle(f"state's particles/{key}", d["particles/" + key], n, broadcast=False)
    j = np.asarray(d["contacts/j"])
    if j.size and (j.min() < 0 or j.max() >= n + MAX_WALLS):
        raise ValueError(f"state's contacts/j has indices outside the {n} particles and "
                         f"{MAX_WALLS} wall slots")

    def arr(key):
        return np.asarray(d[key])

    def need(key, shape, *, kind="f", finite=True, low=None):
        a = arr(key)
        if a.shape != shape or a.dtype.kind not in (("i", "u") if kind == "i" else ("f", "i", "u")):
            raise ValueError(f"state's {key} has shape {a.shape} and dtype {a.dtype}, expected "
                             f"{shape} {'integers' if kind == 'i' else 'numbers'}")
        if kind == "f" and finite and not np.all(np.isfinite(a)):
            raise ValueError(f"state's {key} holds NaN or infinite values")
        if low is not None and a.size and a.min() < low:
            raise ValueError(f"state's {key} holds values below {low}")
        return a

    for key in ("inv_mass", "inv_inertia"):
        need("particles/" + key, (n,), low=0.0)
    need("particles/f_ext", (n, 3))
    layer = need("particles/layer", (n,), kind="i", low=0)
    if layer.size and layer.max() > INT32_MAX:
        raise ValueError(f"state's particles/layer holds values above {INT32_MAX}")
    system = np.asarray(d.get("particles/system", np.zeros(n, np.int32)))
    if system.shape == (n,):
        _check_distinct_centres(np.asarray(d["particles/x"], float), system)
    m = len(arr("contacts/i"))
    ci = need("contacts/i", (m,), kind="i", low=0)
    if m and ci.max() >= n:
        raise ValueError(f"state's contacts/i has indices outside the {n} particles")
    need("contacts/j", (m,), kind="i")
    need("contacts/impulse", (m, 3))
    if "contacts/impulse_old" in d:
        need("contacts/impulse_old", (m, 3))
    need("contacts/gap", (m,))
    # (its values are not checked: a simulation that never stepped holds its pooled
    # buffer's old ones, which nothing reads while its contact count is 0)
    start = need("contacts/start", (n + 1,), kind="i")
    # each particle's contacts are start[i]..start[i+1] of the contact list: a range outside
    # it would be read past the list's end (out of bounds on the device). Without contacts the
    # table is not read: a file written before session 47 by a simulation that never stepped
    # holds its pooled buffer's old values there, and load_state_dict installs zeros instead
    if m and (start.min() < 0 or start.max() > m or np.any(np.diff(start) < 0)):
        raise ValueError(f"state's contacts/start is not a non-decreasing table of offsets into "
                         f"its {m} contacts (values from 0 to {m})")
    b = len(arr("bonds/state"))
    state = need("bonds/state", (b,), kind="i")
    if b and not np.all(np.isin(state, (sk.INTACT, sk.BROKEN_TENSION, sk.BROKEN_SHEAR))):
        raise ValueError(f"state's bonds/state holds values other than {sk.INTACT} (intact), "
                         f"{sk.BROKEN_TENSION} and {sk.BROKEN_SHEAR} (broken)")
    if b:
        for key in ("bonds/i", "bonds/j"):
            if key not in d:
                raise ValueError(f"state has {b} bonds but no {key}")
            a = need(key, (b,), kind="i", low=0)
            if a.max() >= n:
                raise ValueError(f"state's {key} has indices outside the {n} particles")
        bi, bj = arr("bonds/i").astype(np.int64), arr("bonds/j").astype(np.int64)
        if np.any(bi >= bj):
            k = int(np.argmax(bi >= bj))
            raise ValueError(f"state's bond {k} joins particle {bi[k]} to {bj[k]}: a bond joins "
                             "two particles, listed as i < j")
        pairs = bi * n + bj
        if len(np.unique(pairs)) != b:
            raise ValueError("state's bonds list a pair of particles twice")
        if "bonds/area" in d:
            area = need("bonds/area", (b,))
            if np.any(area <= 0):
                raise ValueError("state's bonds/area holds values that are not positive")
    for key in Simulation._BOND_DEFAULTS:
        if "bonds/" + key in d and key not in ("i", "j", "state"):
            shape = (b, 3) if key in Simulation._BOND_VECTORS else (b,)
            need("bonds/" + key, shape, finite=key not in ("broken_time", "broken_pos"))
