"""Scenario files: TOML text -> typed, frozen configuration (pydantic v2 models).

A scenario is data: a name, the seeds (one sample each), the backend, solver, material, bond
and output settings, and a non-empty list of stages (`[[stage]]` tables, `kind = "prepare"` or
`kind = "shear"`). docs/scenarios.md lists every key with its unit, default and meaning.

Invariants:
- Values are SI unless the key name says otherwise (`_mm`, `_MPa`, `_per_min`); the models keep
  the file's numbers and expose SI properties (`cylinder_diameter`, `velocity`, ...).
- Parsing refuses bad input before any simulation starts. Every problem becomes one line
  `FILE: KEY: reason` of a single `ScenarioError` (a ValueError): KEY is a dotted path with
  1-based array indices (`stage[2].vibration_frequency`, `solver.time_step`, `seeds[3]`).
  Refused: unknown keys, wrong types (strict: no string-to-number coercion; an integer is
  accepted where a float is expected), missing required values, out-of-range or non-finite
  numbers, physically impossible combinations (checked by model validators), malformed TOML
  (with its line and column) and missing files.
- Every model is frozen (assignment raises) and forbids extra keys; arrays are stored as tuples.
- Importing this module does not import the solver: `to_settings()` / `to_law()` import
  `tcd.simulation` when called, the packing checks import `tcd.packing` (NumPy only).
"""
from __future__ import annotations

import difflib
import errno
import math
import os
import re
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

from pydantic import (BaseModel, ConfigDict, Field, ValidationError, field_validator,
                      model_validator)

STAGE_KINDS = ("prepare", "shear")
COURSE_NAMES = ("binder", "surface")
NAME_PATTERN = r"^[A-Za-z0-9_.-]+$"
#: a sample may be confined to no less than this fraction of its poured layers' total height
MIN_SAMPLE_FRACTION = 0.9
MAX_PARTICLES_PER_LAYER = 10**7      # spheres per layer, given or derived
#: keys of `Scenario` filled by the loader, not by the file
_LOADER_FIELDS = ("text", "source")


#: bounds outside which `Scenario.doubts` warns (a value likely in another unit):
#: grain density (kg/m^3: pumice to gold), gravity (m/s^2: 10 g), Coulomb coefficient
#: (friction angle 63 deg), bond strength (MPa: structural steel's yield)
PLAUSIBLE_DENSITY = (300.0, 20000.0)
PLAUSIBLE_GRAVITY = 98.1
PLAUSIBLE_FRICTION = 2.0
PLAUSIBLE_STRENGTH_MPA = 500.0

#: the most time steps one phase of a stage may last (2**31 - 1: a 32-bit step count; 5 days
#: of simulated time at the default time step)
MAX_STAGE_STEPS = 2**31 - 1


def _too_many_steps(seconds: float, time_step: float) -> str:
    return (f"{seconds:g} s, more than {MAX_STAGE_STEPS:.2g} time steps of {time_step:g} s "
            "([solver] time_step)")


# --- errors ------------------------------------------------------------------------------------
class ScenarioError(ValueError):
    """A scenario that cannot be run. `problems`: (key, reason) pairs; the message has one line
    `SOURCE: KEY: reason` per problem (`SOURCE: reason` where no key applies)."""

    def __init__(self, source: str, problems):
        self.source = str(source)
        self.problems = tuple((str(k), str(r)) for k, r in problems)
        self.message = "\n".join(f"{self.source}: {k}: {r}" if k else f"{self.source}: {r}"
                                 for k, r in self.problems)
        super().__init__(self.message)

    def __str__(self) -> str:    # an OSError subclass would otherwise format errno/strerror
        return self.message


class ScenarioNotFoundError(ScenarioError, FileNotFoundError):
    """The scenario file (or a file it names) does not exist."""

    def __init__(self, source: str, problems):
        ScenarioError.__init__(self, source, problems)
        self.errno, self.strerror, self.filename = errno.ENOENT, str(self), self.source


class _Problems(ValueError):
    """Raised by model validators: (key, reason) pairs, keys relative to the raising model."""

    def __init__(self, problems):
        self.problems = list(problems)
        super().__init__("; ".join(f"{k}: {r}" for k, r in self.problems))


#: why bond_frame = "end" is refused in single precision (tcd.simulation checks it too)
BOND_FRAME_F32 = ("\"end\" needs f64: in f32 the particle blocks of a grain bonded to a fixed "
                  "one (condition number about 1e5) are solved too coarsely, and with the "
                  "frame's turn the sweeps diverge; use precision = \"f64\", or "
                  "bond_frame = \"start\"")


def _backend_problems(backend, solver) -> list:
    """(key, reason) of the solver settings that the backend cannot run."""
    if backend.precision == "f32" and solver.bond_frame == "end":
        return [("solver.bond_frame", BOND_FRAME_F32)]
    return []


def _raise_if(problems) -> None:
    if problems:
        raise _Problems(problems)


# --- models ------------------------------------------------------------------------------------
class _Model(BaseModel):
    """Frozen, closed, strictly typed; TOML arrays become tuples."""
    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _arrays_as_tuples(cls, data: Any) -> Any:
        # strict mode takes only tuples for tuple fields; TOML gives lists
        if isinstance(data, dict):
            return {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return data


class BackendConfig(_Model):
    """arch: "cpu" or "gpu"; precision: "f64" or "f32" (the real type of every field)."""
    arch: Literal["cpu", "gpu"] = "cpu"
    precision: Literal["f64", "f32"] = "f64"


class SolverConfig(_Model):
    """Moreau-Jean / NLGS settings. time_step H (s); theta in [0.5, 1]; tolerance on the
    convergence measure; convergence: "impulse" (the relative impulse change of a sweep, sum
    |dR| / sum |R|, the default) or "quad" (LMGC90's 'Quad ' check: a pass that updates
    nothing, measuring the velocity corrections the local solves would still make; its
    QuadDV, QuadDVR and |MeanDVoR| must all be below the tolerance; LMGC90's default is
    1.666e-4); max_sweeps per step; check_every: sweeps between convergence checks; schedule: "auto" (serial on CPU, coloured on GPU), "serial",
    "partitioned" (the serial sweep split over `threads` CPU threads; its numbers depend on
    `threads`), "coloured" or "resident" (the coloured schedule's colours, all sweeps of a step
    in one launch: one GPU thread block per system; each system to its own convergence);
    acceleration: "nncg" (conjugate-gradient momentum on the sweeps of the serial,
    partitioned and resident schedules) or "none"; sweep_order: "symmetric" (forward and
    backward sweeps alternate, the default) or "forward" (fewer sweeps on a shear; larger
    overlaps under a vibrating plate; the coloured and resident schedules always sweep
    forward);
    warm_start_extrapolation: c in [0, 1], each bond and lasting contact starts the step from
    R_n + c (R_n - R_n-1) (0: from R_n, the default);
    alert_ratio: alert distance / smallest radius; gravity (m/s^2, along -z);
    overlap_slop: overlap (fraction of the smallest diameter) below which the end-of-step
    position projection leaves contacts alone; projection_passes: its sweeps (0: off);
    bond_blocks: relax the bonds particle by particle, each particle's bonds solved exactly
    (true, the default; false: bond by bond, which stalls on the bonds of light grains);
    bond_frame: "start" (a bond's normal force along the line of centres of the step's start,
    the default) or "end" (turned with it over the step: stable for a grain rolling about a
    loaded bond at any time step; needs acceleration = "none");
    neighbour_skin: skin of the broad phase's neighbour list / smallest radius (cost only:
    the contacts are the same for any skin; fast grains get room for about two steps of
    their reach); colouring (coloured schedule): "greedy" (serial, fewest colours), "rounds"
    (parallel) or "auto" (greedy on the CPU, rounds on the GPU)."""
    # bounds: sane physics, and integers that fit the solver's 32-bit kernel arguments
    time_step: float = Field(2e-4, ge=1e-7, le=0.1)
    theta: float = Field(1.0, ge=0.5, le=1.0)
    tolerance: float = Field(1e-4, gt=0)
    max_sweeps: int = Field(1000, ge=1, le=10**7)
    check_every: int = Field(1, ge=1, le=10**7)
    convergence: Literal["impulse", "quad"] = "impulse"
    schedule: Literal["auto", "serial", "partitioned", "coloured", "resident"] = "auto"
    threads: int = Field(2, ge=1, le=64)
    acceleration: Literal["nncg", "none"] = "nncg"
    sweep_order: Literal["forward", "symmetric"] = "symmetric"
    warm_start_extrapolation: float = Field(0.0, ge=0.0, le=1.0)
    alert_ratio: float = Field(0.1, gt=0)
    gravity: float = Field(9.81, ge=0, le=1e4)    # up to about 1000 g (a centrifuge)
    overlap_slop: float = Field(0.002, ge=0)
    projection_passes: int = Field(2, ge=0, le=10**6)
    bond_blocks: bool = True
    bond_frame: Literal["start", "end"] = "start"
    neighbour_skin: float = Field(2.0, ge=0)
    colouring: Literal["auto", "greedy", "rounds"] = "auto"

    @model_validator(mode="after")
    def _check(self) -> "SolverConfig":
        problems = []
        if self.check_every > self.max_sweeps:
            problems.append(("check_every", f"must not exceed max_sweeps ({self.max_sweeps}), "
                                            f"got {self.check_every}: convergence would never "
                                            "be checked"))
        if self.bond_frame == "end" and self.acceleration != "none":
            problems.append(("bond_frame", "\"end\" needs acceleration = \"none\" (the "
                                           "conjugate-gradient momentum does not move the "
                                           "bonds' turns, and with it the sweeps diverge)"))
        if self.schedule == "resident" and self.convergence == "quad":
            # (the simulation refuses it too; here, before a run writes anything)
            problems.append(("convergence", "\"quad\" is not measured by the resident schedule "
                                            "(it has no 'Quad ' check pass): use convergence = "
                                            "\"impulse\", or schedule = \"coloured\""))
        _raise_if(problems)
        return self

    def to_settings(self):
        """The engine's `tcd.simulation.SolverSettings` for these values."""
        from .simulation import SolverSettings
        return SolverSettings(time_step=self.time_step, theta=self.theta,
                              tolerance=self.tolerance, max_sweeps=self.max_sweeps,
                              check_every=self.check_every, convergence=self.convergence,
                              schedule=self.schedule,
                              threads=self.threads,
                              acceleration=self.acceleration, sweep_order=self.sweep_order,
                              warm_start_extrapolation=self.warm_start_extrapolation,
                              alert_ratio=self.alert_ratio,
                              gravity=(0.0, 0.0, -self.gravity), overlap_slop=self.overlap_slop,
                              projection_passes=self.projection_passes,
                              bond_blocks=self.bond_blocks, bond_frame=self.bond_frame,
                              neighbour_skin=self.neighbour_skin, colouring=self.colouring)


class MaterialConfig(_Model):
    """density of the grains (kg/m^3); friction: particle-particle Coulomb coefficient;
    wall_friction: particle-wall coefficient during preparation."""
    density: float = Field(2600.0, ge=1.0, le=1e5)
    friction: float = Field(0.7, ge=0)
    wall_friction: float = Field(0.0, ge=0)


class BondConfig(_Model):
    """Burgers bonds created at the start of a shear stage. mode: "paper" (secant stiffness
    1/J(age)) or "burgers" (incremental four-parameter model); Maxwell and Kelvin stiffness (N/m)
    and viscosity (N s/m) of the normal law; poisson_ratio sets the tangential law;
    yield_stress_MPa: bond strength; gap_tolerance_mm: largest gap of a pair still bonded;
    friction_after_break: Coulomb coefficient of a broken bond."""
    mode: Literal["paper", "burgers"] = "paper"
    maxwell_stiffness: float = Field(2e6, gt=0)
    maxwell_viscosity: float = Field(2e7, gt=0)
    kelvin_stiffness: float = Field(2e6, gt=0)
    kelvin_viscosity: float = Field(2e7, gt=0)
    poisson_ratio: float = Field(0.3, gt=-1.0, lt=0.5)
    yield_stress_MPa: float = Field(2.7, gt=0)
    gap_tolerance_mm: float = Field(0.01, ge=0)
    friction_after_break: float = Field(0.7, ge=0)

    @property
    def yield_stress(self) -> float:
        """Bond strength (Pa)."""
        return self.yield_stress_MPa * 1e6

    @property
    def gap_tolerance(self) -> float:
        """Largest gap of a bonded pair (m)."""
        return self.gap_tolerance_mm * 1e-3

    def to_law(self, mode: Optional[str] = None):
        """The engine's `tcd.simulation.BondLaw`; `mode` overrides `self.mode` (a shear stage's
        `bond_mode`) when not None."""
        from .simulation import BondLaw
        return BondLaw(mode=self.mode if mode is None else mode,
                       maxwell_stiffness=self.maxwell_stiffness,
                       maxwell_viscosity=self.maxwell_viscosity,
                       kelvin_stiffness=self.kelvin_stiffness,
                       kelvin_viscosity=self.kelvin_viscosity,
                       poisson_ratio=self.poisson_ratio, yield_stress=self.yield_stress,
                       friction_after_break=self.friction_after_break)


class OutputConfig(_Model):
    """snapshot_every: simulated seconds between state snapshots; checkpoint_every_s: wall-clock
    seconds between checkpoints; series_every: steps between time-series records."""
    snapshot_every: float = Field(0.05, gt=0)
    checkpoint_every_s: float = Field(60.0, gt=0)
    series_every: int = Field(1, ge=1, le=10**9)


class PrepareStage(_Model):
    """Pour and vibrate `courses` (bottom first) layer by layer in a cylinder, then confine the
    sample between two plates `sample_height_mm` apart. Each layer has `particles_per_layer`
    spheres (0: enough to fill `layer_height_mm` at `packing_fraction`); sphere sizes follow the
    course's table (PHYSICS.md section 7) times `size_scale`. Spheres start at lattice sites
    (`lattice_jitter_mm` horizontal offsets) in a column up to `column_height_mm` and fall until
    their mass-weighted rms speed sqrt(2 KE / M) is below `settle_speed` or `max_settle_time`
    has passed; the top plate then
    vibrates (`vibration_amplitude_mm`, `vibration_frequency`, `vibration_duration`) and holds
    the layer at its height until settled (at most `max_hold_time`). The plate is servo-
    controlled: it backs off while it pushes with more than `plate_force_factor` times the
    sample's weight."""
    kind: Literal["prepare"]
    cylinder_diameter_mm: float = Field(150.0, gt=0)
    layer_height_mm: float = Field(60.0, gt=0)
    packing_fraction: float = Field(0.587, gt=0, lt=0.74)
    courses: tuple[Literal["binder", "surface"], ...] = Field(("binder", "surface"),
                                                              min_length=1, max_length=4)
    particles_per_layer: int = Field(0, ge=0, le=MAX_PARTICLES_PER_LAYER)
    size_scale: float = Field(1.0, ge=1e-3, le=1e3)
    column_height_mm: float = Field(1600.0, gt=0)
    lattice_jitter_mm: float = Field(0.2, ge=0)
    settle_speed: float = Field(0.005, gt=0, le=1.0)   # m/s: "negligible" kinetic energy
    max_settle_time: float = Field(3.0, gt=0)
    vibration_amplitude_mm: float = Field(6.0, ge=0)
    vibration_frequency: float = Field(30.0, gt=0)
    vibration_duration: float = Field(1.0, ge=0)
    sample_height_mm: float = Field(120.0, gt=0)
    max_hold_time: float = Field(0.5, gt=0)
    plate_force_factor: float = Field(3.0, gt=0)

    @property
    def cylinder_diameter(self) -> float:
        return self.cylinder_diameter_mm * 1e-3

    @property
    def layer_height(self) -> float:
        return self.layer_height_mm * 1e-3

    @property
    def column_height(self) -> float:
        return self.column_height_mm * 1e-3

    @property
    def lattice_jitter(self) -> float:
        return self.lattice_jitter_mm * 1e-3

    @property
    def vibration_amplitude(self) -> float:
        return self.vibration_amplitude_mm * 1e-3

    @property
    def sample_height(self) -> float:
        return self.sample_height_mm * 1e-3

    def largest_diameter(self) -> float:
        """Diameter (m) of the largest size class present in any of the courses, scaled."""
        from . import packing
        return max(float(packing.DIAMETERS[packing.COURSES[c] > 0].max())
                   for c in self.courses) * self.size_scale

    def layer_particle_count(self, course: str) -> int:
        """Spheres in one layer of `course`: `particles_per_layer`, or (when 0) enough spheres of
        the scaled size table to fill the layer's cylinder at `packing_fraction` (at least 1)."""
        if self.particles_per_layer > 0:
            return self.particles_per_layer
        from . import packing
        n = packing.count_for_layer(course, self.cylinder_diameter, self.layer_height,
                                    self.packing_fraction)
        return max(1, int(round(n / self.size_scale**3)))

    @model_validator(mode="after")
    def _check(self) -> "PrepareStage":
        problems = []
        d_max = self.largest_diameter() * 1e3
        if d_max >= self.cylinder_diameter_mm:
            problems.append(("cylinder_diameter_mm",
                             f"particles larger than the cylinder: the largest sphere is "
                             f"{d_max:g} mm (size table x size_scale {self.size_scale:g}), the "
                             f"cylinder diameter {self.cylinder_diameter_mm:g} mm"))
        need = len(self.courses) * self.layer_height_mm * MIN_SAMPLE_FRACTION
        if self.sample_height_mm < need:
            problems.append(("sample_height_mm",
                             f"{self.sample_height_mm:g} mm is below {MIN_SAMPLE_FRACTION:g} x "
                             f"{len(self.courses)} courses x layer_height_mm "
                             f"{self.layer_height_mm:g} = {need:g} mm: rigid grains cannot be "
                             f"compressed that much"))
        if self.vibration_amplitude_mm >= self.layer_height_mm:
            problems.append(("vibration_amplitude_mm",
                             f"{self.vibration_amplitude_mm:g} mm must be smaller than "
                             f"layer_height_mm ({self.layer_height_mm:g} mm)"))
        if not problems and self.particles_per_layer == 0:
            for course in self.courses:
                try:
                    n = self.layer_particle_count(course)
                except OverflowError:       # a layer's volume beyond a float: as many
                    n = float("inf")
                if n > MAX_PARTICLES_PER_LAYER:
                    problems.append(("size_scale",
                                     f"{n:.3g} spheres in a {course} layer (the layer filled at "
                                     f"packing_fraction with spheres x size_scale "
                                     f"{self.size_scale:g}): at most {MAX_PARTICLES_PER_LAYER:.0e}"))
                    break
        if not problems:
            problems += self._column_problems()
        _raise_if(problems)
        return self

    def _column_problems(self) -> list:
        """Each course must fit on the lattice of its pouring column (as tcd.packing builds
        it), above the layers poured before it."""
        import numpy as np

        from . import packing
        rng = np.random.default_rng(0)
        for k, course in enumerate(self.courses):
            base = k * self.layer_height
            room = self.column_height - base
            radii = packing.course_radii(course, self.layer_particle_count(course), rng)
            key = "column_height_mm"
            try:
                if room <= 0:
                    raise ValueError(f"no room above the {k} layer(s) poured before it")
                packing.lattice_column(radii * self.size_scale, self.cylinder_diameter, base, rng,
                                       max_height=room, jitter=self.lattice_jitter)
            except ValueError as exc:
                if "column diameter" in str(exc) or "too narrow" in str(exc):
                    key = "cylinder_diameter_mm"
                if room > 0 and self.lattice_jitter > 0:
                    try:                # fits without the jitter: the jitter is the problem
                        packing.lattice_column(radii * self.size_scale, self.cylinder_diameter,
                                               base, rng, max_height=room, jitter=0.0)
                        key = "lattice_jitter_mm"
                    except ValueError:
                        pass
                return [(key, f"course {k + 1} ({course}, {len(radii)} spheres) does not fit "
                              f"its pouring column: {exc}")]
        return []


class ShearStage(_Model):
    """Leutner shear test: the cylinder is replaced by two rings (`ring_height_mm` each,
    `gap_mm` apart at the sample's mid-height); the upper ring and the top plate move
    horizontally at `velocity_mm_per_min` until `displacement_mm`. Bonds (the `[bond]` law,
    `bond_mode` overriding its mode) are created between touching particles at the start.
    `sample`: "" for the sample of the preceding prepare stage, else a state file path
    (relative paths are relative to the scenario file's directory); `{seed}` in it is replaced
    by each sample's seed, so a study can shear a set of prepared samples. `tolerance` and
    `max_sweeps`: the solver's during this stage (default: those of `[solver]`); a bonded
    sample needs a tighter tolerance than a pour (docs/measurements.md, "Convergence of the
    shear"). `renumber`: number
    the particles along the shear (x) before bonding (`Simulation.renumber`): cheaper steps on
    the partitioned schedule (on one thread it depends on the sweep order: docs/performance.md,
    "Solver settings that change the speed"), and numbers that differ at the level of the solver's tolerance; each particle's index in the sample is kept (particles/sample_index).
    `ring_edges`: where a ring ends, "rim" (its inner circle: a grain beyond the ring's end
    touches it only there) or "extended" (the ring's wall reaches one grain radius further:
    the geometry of sessions 1-31, which the calibration scenarios keep; the study's use "rim";
    walls.py)."""
    kind: Literal["shear"]
    displacement_mm: float = Field(2.5, gt=0)
    velocity_mm_per_min: float = Field(50.0, gt=0)
    ring_height_mm: float = Field(60.0, gt=0)
    gap_mm: float = Field(1.0, ge=0)
    wall_friction: float = Field(0.0, ge=0)
    smoothing_window_mm: float = Field(0.1, gt=0)
    bond_mode: Optional[Literal["paper", "burgers"]] = None
    tolerance: Optional[float] = Field(None, gt=0)
    max_sweeps: Optional[int] = Field(None, ge=1, le=10**7)
    sample: str = ""
    renumber: bool = False
    ring_edges: Literal["rim", "extended"] = "rim"

    @property
    def displacement(self) -> float:
        return self.displacement_mm * 1e-3

    @property
    def velocity(self) -> float:
        """Speed of the upper ring (m/s)."""
        return self.velocity_mm_per_min * 1e-3 / 60.0

    @property
    def duration(self) -> float:
        """Simulated time of the test (s)."""
        return self.displacement / self.velocity

    @property
    def ring_height(self) -> float:
        return self.ring_height_mm * 1e-3

    @property
    def gap(self) -> float:
        return self.gap_mm * 1e-3

    @property
    def smoothing_window(self) -> float:
        return self.smoothing_window_mm * 1e-3

    @model_validator(mode="after")
    def _check(self) -> "ShearStage":
        problems = []
        if self.gap_mm >= self.ring_height_mm:
            problems.append(("gap_mm", f"shear gap {self.gap_mm:g} mm must be smaller than "
                                       f"ring_height_mm ({self.ring_height_mm:g} mm)"))
        if self.smoothing_window_mm >= self.displacement_mm:
            problems.append(("smoothing_window_mm",
                             f"{self.smoothing_window_mm:g} mm must be smaller than "
                             f"displacement_mm ({self.displacement_mm:g} mm)"))
        _raise_if(problems)
        return self


Stage = Annotated[Union[PrepareStage, ShearStage], Field(discriminator="kind")]
_STAGE_MODELS = {"prepare": PrepareStage, "shear": ShearStage}


class Scenario(_Model):
    """One scenario file. name: run name (letters, digits, '_', '.', '-'; default output
    runs/<name>); seeds: one sample per seed; stages: run in order, each on the previous one's
    result. text: the file's text as read; source: its path ("<string>" when parsed from text)."""
    name: str = Field(pattern=NAME_PATTERN)
    description: str = ""
    seeds: tuple[Annotated[int, Field(ge=0)], ...] = Field((1,), min_length=1)
    backend: BackendConfig = Field(default_factory=BackendConfig)
    solver: SolverConfig = Field(default_factory=SolverConfig)
    material: MaterialConfig = Field(default_factory=MaterialConfig)
    bond: BondConfig = Field(default_factory=BondConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    stages: tuple[Stage, ...] = Field(alias="stage", min_length=1)
    text: str = Field("", repr=False)
    source: str = "<string>"

    @field_validator("name")
    @classmethod
    def _name_is_not_a_directory_alias(cls, name: str) -> str:
        if name in (".", ".."):
            raise ValueError(f"must not be {name!r}: it names the output directory runs/<name>")
        return name

    @model_validator(mode="after")
    def _check(self) -> "Scenario":
        problems = []
        seen = set()
        for k, seed in enumerate(self.seeds):
            if seed in seen:
                problems.append((f"seeds[{k + 1}]", f"duplicate seed {seed}: each seed makes "
                                                    f"one sample"))
            seen.add(seed)
        prepared = None
        kinds = [stage.kind for stage in self.stages]
        for kind in ("prepare", "shear"):
            if kinds.count(kind) > 1:
                second = [k for k, x in enumerate(kinds) if x == kind][1]
                problems.append((f"stage[{second + 1}].kind",
                                 f"a second {kind} stage: a scenario has at most one prepare "
                                 "stage and one shear stage (a second one would overwrite the "
                                 f"first one's {kind}_series and mix their samples)"))
        problems += _backend_problems(self.backend, self.solver)
        if "prepare" in kinds and "shear" in kinds and kinds.index("prepare") > kinds.index("shear"):
            problems.append((f"stage[{kinds.index('prepare') + 1}].kind",
                             "a prepare stage after the shear stage: prepare the sample first"))
        dt = self.solver.time_step
        for k, stage in enumerate(self.stages):
            key = f"stage[{k + 1}]"
            if isinstance(stage, PrepareStage):
                prepared = stage
                # (a 1e300 s vibration or 1e-300 mm/min shear was accepted and ran for ever)
                for name in ("max_settle_time", "vibration_duration", "max_hold_time"):
                    if getattr(stage, name) / dt > MAX_STAGE_STEPS:
                        problems.append((f"{key}.{name}", _too_many_steps(getattr(stage, name), dt)))
                # (1e300 Hz flung the grains to infinity: "particle positions must be finite")
                if stage.vibration_frequency * 2 * dt > 1:
                    problems.append((f"{key}.vibration_frequency",
                                     f"{stage.vibration_frequency:g} Hz is above the "
                                     f"{0.5 / dt:g} Hz that time steps of {dt:g} s can "
                                     "follow (two steps per period)"))
                continue
            if stage.duration / dt > MAX_STAGE_STEPS:
                problems.append((f"{key}.velocity_mm_per_min",
                                 f"{stage.velocity_mm_per_min:g} mm/min takes "
                                 f"{_too_many_steps(stage.duration, dt)}, for displacement_mm "
                                 f"({stage.displacement_mm:g} mm)"))
            if stage.max_sweeps is not None and self.solver.check_every > stage.max_sweeps:
                problems.append((f"{key}.max_sweeps",
                                 f"{stage.max_sweeps} is below [solver] check_every "
                                 f"({self.solver.check_every}): convergence would be checked "
                                 "only at the sweep limit"))
            if stage.duration < self.solver.time_step:
                problems.append((f"{key}.velocity_mm_per_min",
                                 f"{stage.velocity_mm_per_min:g} mm/min covers displacement_mm "
                                 f"({stage.displacement_mm:g} mm) in {stage.duration:.3g} s, less "
                                 f"than one time step ({self.solver.time_step:g} s)"))
            if stage.sample:
                if prepared is not None:
                    problems.append((f"{key}.sample",
                                     "a shear stage after a prepare stage shears the sample "
                                     "that stage makes; this sample file would be ignored: "
                                     "remove `sample`, or the prepare stage"))
                continue
            if prepared is None:
                problems.append((f"{key}.sample", "a shear stage needs a preceding prepare "
                                                  "stage or a sample path"))
                continue
            if stage.displacement_mm >= prepared.cylinder_diameter_mm:
                problems.append((f"{key}.displacement_mm",
                                 f"{stage.displacement_mm:g} mm is not smaller than the "
                                 f"{prepared.cylinder_diameter_mm:g} mm diameter of the "
                                 f"preceding prepare stage's mould: the upper ring would "
                                 f"leave the lower one"))
            if 2 * stage.ring_height_mm < prepared.sample_height_mm:     # (both: one line each)
                problems.append((f"{key}.ring_height_mm",
                                 f"two rings of {stage.ring_height_mm:g} mm cannot confine the "
                                 f"{prepared.sample_height_mm:g} mm sample of the preceding "
                                 f"prepare stage (ring_height_mm must be at least half of "
                                 f"sample_height_mm)"))
        _raise_if(problems)
        return self

    def doubts(self) -> list[tuple[str, str]]:
        """(key, reason) of values that are accepted but unlikely to be meant: a number in
        another unit than the key's (a density in g/cm^3, gravity in mm/s^2, a strength in
        Pa under a `_MPa` key, a friction angle in degrees for a coefficient). `tcd run` prints
        each as a warning and runs the scenario as written."""
        out = []
        density = self.material.density
        if not PLAUSIBLE_DENSITY[0] <= density <= PLAUSIBLE_DENSITY[1]:
            hint = (f" (g/cm^3? {density:g} g/cm^3 is {density * 1e3:g} kg/m^3)"
                    if PLAUSIBLE_DENSITY[0] <= density * 1e3 <= PLAUSIBLE_DENSITY[1] else "")
            out.append(("material.density",
                        f"{density:g} kg/m^3 is outside {PLAUSIBLE_DENSITY[0]:g}-"
                        f"{PLAUSIBLE_DENSITY[1]:g} kg/m^3, the range of solid grains; the key "
                        f"is in kg/m^3 (aggregate about 2600-3000){hint}"))
        g = self.solver.gravity
        if g > PLAUSIBLE_GRAVITY:
            hint = (f" (mm/s^2? {g:g} mm/s^2 is {g * 1e-3:g} m/s^2)"
                    if 1.0 <= g * 1e-3 <= PLAUSIBLE_GRAVITY else "")
            out.append(("solver.gravity",
                        f"{g:g} m/s^2 is {g / 9.81:.0f} times the Earth's 9.81 m/s^2; the key is "
                        f"in m/s^2{hint}; ignore this for a centrifuge"))
        frictions = [("material.friction", self.material.friction),
                     ("material.wall_friction", self.material.wall_friction),
                     ("bond.friction_after_break", self.bond.friction_after_break)]
        frictions += [(f"stage[{k + 1}].wall_friction", stage.wall_friction)
                      for k, stage in enumerate(self.stages) if isinstance(stage, ShearStage)]
        for key, mu in frictions:
            if mu > PLAUSIBLE_FRICTION:
                hint = (f" (an angle in degrees? tan({mu:g} deg) = "
                        f"{math.tan(math.radians(mu)):.3g})" if mu < 90 else "")
                out.append((key, f"a Coulomb coefficient of {mu:g} (above "
                                 f"{PLAUSIBLE_FRICTION:g}: friction angle "
                                 f"{math.degrees(math.atan(mu)):.1f} deg){hint}; ignore this "
                                 "for walls meant to be rough (no slip)"))
        strength = self.bond.yield_stress_MPa
        if strength > PLAUSIBLE_STRENGTH_MPA:
            out.append(("bond.yield_stress_MPa",
                        f"{strength:g} MPa is above {PLAUSIBLE_STRENGTH_MPA:g} MPa, stronger "
                        f"than steel; the key is in MPa (kPa? {strength:g} kPa is "
                        f"{strength * 1e-3:g} MPa; Pa? {strength:g} Pa is {strength * 1e-6:g} "
                        "MPa; the default is 2.7 MPa)"))
        return out

    def with_overrides(self, arch: Optional[str] = None,
                       precision: Optional[str] = None) -> "Scenario":
        """A copy with the backend's arch and/or precision replaced (None: keep)."""
        update = {k: v for k, v in (("arch", arch), ("precision", precision)) if v is not None}
        if not update:
            return self
        backend = _validate(BackendConfig, {**self.backend.model_dump(), **update},
                            f"{self.source} (command-line override)", prefix="backend")
        problems = _backend_problems(backend, self.solver)
        if problems:
            raise ScenarioError(f"{self.source} (command-line override)", problems)
        return self.model_copy(update={"backend": backend})


    def with_seeds(self, seeds: Optional[list] = None) -> "Scenario":
        """A copy that runs only `seeds`, each of which must be one of the scenario's seeds
        (None: keep all). Lets a study be split across invocations or machines."""
        if not seeds:
            return self
        unknown = [s for s in seeds if s not in self.seeds]
        if unknown:
            raise ScenarioError(self.source, [("seeds", f"--seeds {unknown} not among the scenario's seeds {self.seeds}")])
        if len(set(seeds)) != len(seeds):
            raise ScenarioError(self.source, [("seeds", f"--seeds {seeds} repeats a seed")])
        return self.model_copy(update={"seeds": list(seeds)})


# --- settings from the command line (tcd run --set KEY=VALUE) --------------------------------
_SET_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*(\[[1-9][0-9]*\])?")


def parse_setting(text: str) -> tuple[str, object]:
    """`KEY=VALUE` of `tcd run --set` as (KEY, value): VALUE read as a TOML value (1.6, 1e-6,
    true, [2, 3], "text"), or else taken as a bare string (forward). Raises ValueError naming
    what is wrong."""
    key, sep, raw = text.partition("=")
    key, raw = key.strip(), raw.strip()
    if not sep or not key or not raw:
        raise ValueError(f"expected KEY=VALUE (e.g. bond.yield_stress_MPa=1.6), got {text!r}")
    if not all(_SET_KEY.fullmatch(part) for part in key.split(".")):
        raise ValueError(f"{key!r} is not a scenario key: names separated by dots, a stage as "
                         "stage[K] counted from 1 (e.g. solver.tolerance, stage[2].displacement_mm)")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw             # a bare word: a string
    return key, value


def apply_settings(text: str, settings, source: str = "<string>") -> str:
    """The scenario TOML `text` with each (KEY, value) of `settings` set (tcd run --set), its
    comments and layout kept (tomlkit), and a first comment line naming the settings
    (SETTINGS_HEADER, then the words of settings_words): the text the run stores and every
    process of it reads. A key the scenario lacks is added (and then
    checked as every key is). Raises ScenarioError naming the key that cannot be set."""
    settings = list(settings)
    if not settings:
        return text
    try:
        import tomlkit
    except ImportError:     # an install older than --set: its dependencies not updated
        raise ScenarioError(source, [("", "--set needs the tomlkit package, a dependency of "
                                          "tcd since session 58: reinstall tcd "
                                          "(pip install -e .) or pip install tomlkit")]) from None
    try:
        doc = tomlkit.parse(text.removeprefix("\ufeff"))
    except Exception as exc:        # tomlkit's ParseError: as tomllib would report it
        parse_scenario(text, source, resolve_samples=False)
        raise ScenarioError(source, [("", f"malformed TOML: {exc}")]) from None
    problems = []
    seen: dict = {}
    for key, value in settings:
        if key in seen:
            problems.append((key, f"set twice by --set ({_shown_value(seen[key])}, then "
                                  f"{_shown_value(value)}): give each key once"))
        seen[key] = value
    if problems:
        raise ScenarioError(source, problems)
    for key, value in settings:
        table, parts = doc, key.split(".")
        try:
            for depth, part in enumerate(parts):
                name, _, index = part.partition("[")
                last = depth == len(parts) - 1
                if index:
                    k = int(index.rstrip("]"))
                    items = table.get(name) if hasattr(table, "get") else None
                    if not isinstance(items, list) or not 1 <= k <= len(items):
                        count = len(items) if isinstance(items, list) else 0
                        raise KeyError(f"no {name}[{k}]: the scenario has {count} "
                                       f"[[{name}]] table{'' if count == 1 else 's'}")
                    if last and not isinstance(value, dict):
                        # (a value in an array of tables: tomlkit failed to write it, a
                        # traceback: session 72's review)
                        raise KeyError(f"{name}[{k}] is a [[{name}]] table: set one of its "
                                       f"keys ({name}[{k}].KEY=VALUE), or give a table "
                                       f"({name}[{k}]={{KEY = VALUE, ...}})")
                    if last:
                        items[k - 1] = value
                    else:
                        table = items[k - 1]
                elif last:
                    table[name] = value
                else:
                    if name not in table:
                        table[name] = tomlkit.table()
                    table = table[name]
                if not last and isinstance(table, list):
                    raise KeyError(f"{name} holds [[{name}]] tables: name one as {name}[K], "
                                   "counted from 1")
                if not last and not hasattr(table, "get"):
                    raise KeyError(f"{'.'.join(parts[:depth + 1])} is a value, not a table")
        except KeyError as exc:
            problems.append((key, f"--set: {exc.args[0]}"))
    if problems:
        raise ScenarioError(source, problems)
    return f"{SETTINGS_HEADER}{settings_words(settings)}\n" + tomlkit.dumps(doc)


#: the first line of a scenario text with `tcd run --set` settings applied, before the words
SETTINGS_HEADER = "# tcd run with "


def settings_words(settings) -> str:
    """`--set KEY=VALUE ...` of (KEY, value) pairs, quoted for a POSIX shell."""
    import shlex
    import tomlkit
    return shlex.join(word for key, value in settings
                      for word in ("--set", f"{key}={tomlkit.item(value).as_string()}"))


def text_settings(text: str) -> str:
    """The `--set ...` words a stored scenario text was made with ("" when none)."""
    first = text.partition("\n")[0]
    return first[len(SETTINGS_HEADER):].strip() if first.startswith(SETTINGS_HEADER) else ""


def flat_keys(value, prefix: str = "") -> dict:
    """A scenario dict as {dotted key: leaf}, arrays of tables numbered from 1
    (`stage[2].wall_friction`, as the scenario's own errors name them)."""
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            out.update(flat_keys(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        out = {}
        for k, v in enumerate(value, start=1):
            out.update(flat_keys(v, f"{prefix}[{k}]"))
        return out
    return {prefix: value}


def describe(scenario: "Scenario") -> str:
    """`tcd info SCENARIO.toml`: what a run of the checked scenario would run, before it runs:
    its seeds and stages, the sample files a shear reads, the values likely in another unit
    (`doubts`), and every setting, defaults filled in, those the file (or --set) writes marked
    with `*`."""
    data = scenario.model_dump(mode="json", by_alias=True, exclude={"text", "source"})
    try:
        written = set(flat_keys(tomllib.loads(scenario.text)))
    except tomllib.TOMLDecodeError:
        written = set()
    kinds = ", ".join(st.kind for st in scenario.stages) or "none"
    lines = [f"{scenario.source}: a valid tcd scenario {scenario.name!r}: seeds "
             f"{', '.join(map(str, scenario.seeds))}; stages {kinds}"]
    for k, stage in enumerate(scenario.stages, start=1):
        if isinstance(stage, PrepareStage):
            counts = [stage.layer_particle_count(course) for course in stage.courses]
            lines.append(f"stage[{k}] prepares {' + '.join(map(str, counts))}"
                         f"{f' = {sum(counts)}' if len(counts) > 1 else ''} grains a sample "
                         f"(courses {', '.join(stage.courses)}, bottom first)")
        if isinstance(stage, ShearStage):
            steps = stage.displacement_mm / stage.velocity_mm_per_min * 60 / scenario.solver.time_step
            test = (f"to {stage.displacement_mm:g} mm at {stage.velocity_mm_per_min:g} mm/min, "
                    f"{steps:.0f} time steps")
            if stage.sample:        # one per seed, each read by `tcd info` (runner.check_samples)
                count = len(scenario.seeds)
                lines.append(f"stage[{k}] shears the sample files {stage.sample} "
                             f"({count} file{'' if count == 1 else 's'}, all present and read "
                             "as prepared samples) " + test)
            else:
                lines.append(f"stage[{k}] shears the sample prepared before it " + test)
    lines += [f"warning: {key}: {reason}" for key, reason in scenario.doubts()]
    rows = [(key, value) for key, value in flat_keys(data).items()]
    width = max((len(key) for key, _ in rows), default=0)
    lines.append("settings (* written in the file or by --set; the others are defaults):")
    lines += [f"{'*' if key in written else ' '} {key:<{width}}  {_shown_value(value)}"
              for key, value in rows]
    return "\n".join(lines)


def _shown_value(value) -> str:
    if isinstance(value, float):
        return f"{value:.12g}"
    if isinstance(value, list):
        return "[" + ", ".join(_shown_value(v) for v in value) + "]"
    return str(value)


# --- parsing -----------------------------------------------------------------------------------
def load_scenario(path, settings=(), *, seeds=None) -> Scenario:
    """Read and validate the scenario file at `path` (see parse_scenario), with `settings`
    ((KEY, value) pairs of `tcd run --set`) applied first (apply_settings); `seeds` (`tcd run
    --seeds`): the seeds whose sample files must exist (default: all the scenario's)."""
    source = os.fspath(path)
    try:
        raw = Path(source).read_bytes()
    except FileNotFoundError:
        raise ScenarioNotFoundError(source, [("", "no such scenario file")]) from None
    except IsADirectoryError:
        raise ScenarioError(source, [("", "is a directory, not a scenario file")]) from None
    except OSError as exc:
        raise ScenarioError(source, [("", f"cannot read the scenario file: {exc.strerror}")]) \
            from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ScenarioError(source, [("", f"not UTF-8 text (byte {exc.start}): TOML files "
                                          f"are UTF-8")]) from None
    return parse_scenario(apply_settings(text, settings, source), source, seeds=seeds)


def parse_scenario(text: str, source: str = "<string>", *, resolve_samples: bool = True,
                   seeds=None) -> Scenario:
    """Validate the TOML `text` of a scenario; `source` names it in error messages and is the
    base directory of relative `sample` paths (the working directory for "<...>" sources).
    Raises ScenarioError listing every problem found. `resolve_samples=False` leaves `sample`
    paths as written and does not look for the files (to compare two runs' scenarios);
    `seeds`: the seeds whose sample files must exist (default: all the scenario's; a run of
    some of them, `tcd run --seeds`, needs only theirs)."""
    source = str(source)
    text = text.removeprefix("\ufeff")      # a byte-order mark some editors write
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        message = str(exc)
        where = re.search(r"\s*\((at line \d+, column \d+|at end of document)\)\s*$", message)
        key = where.group(1).removeprefix("at ") if where else ""
        reason = message[:where.start()] if where else message
        raise ScenarioError(source, [(key, f"malformed TOML: {reason}")]) from None
    reserved = [(k, _unknown_key_reason(k, ())) for k in _LOADER_FIELDS if k in data]
    data = {k: v for k, v in data.items() if k not in _LOADER_FIELDS}
    try:
        scenario = Scenario.model_validate({**data, "text": text, "source": source})
    except ValidationError as exc:
        raise ScenarioError(source, reserved + _problems(exc)) from None
    if reserved:
        raise ScenarioError(source, reserved)
    return _resolve_samples(scenario, seeds) if resolve_samples else scenario


def _resolve_samples(scenario: Scenario, seeds=None) -> Scenario:
    """Make shear `sample` paths absolute (relative to the scenario file) and check that the
    files of `seeds` (default: every seed of the scenario) exist; a seed not in the scenario
    is left to `Scenario.with_seeds` to report."""
    seeds = scenario.seeds if seeds is None else [s for s in seeds if s in scenario.seeds]
    base = Path.cwd() if scenario.source.startswith("<") else Path(scenario.source).parent
    stages, missing = [], []
    for k, stage in enumerate(scenario.stages):
        if isinstance(stage, ShearStage) and stage.sample:
            path = (base / stage.sample).resolve()
            for seed in seeds or scenario.seeds[:1]:       # (the placeholder checked once)
                try:
                    each = Path(str(path).format(seed=seed))
                except (KeyError, IndexError, ValueError) as exc:
                    missing.append((f"stage[{k + 1}].sample", f"bad placeholder in {stage.sample!r}: "
                                                              f"only {{seed}} is known ({exc})"))
                    break
                if seed not in seeds:
                    continue
                if each.is_dir():
                    missing.append((f"stage[{k + 1}].sample", f"{each} is a directory, not a "
                                                              "sample file"))
                elif not each.is_file():
                    missing.append((f"stage[{k + 1}].sample", f"no such sample file: {each}"))
            stage = stage.model_copy(update={"sample": str(path)})
        stages.append(stage)
    if missing:
        raise ScenarioNotFoundError(scenario.source, missing)
    return scenario.model_copy(update={"stages": tuple(stages)})


def _validate(model, data: dict, source: str, *, prefix: str = ""):
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        problems = [(f"{prefix}.{k}" if prefix and k else (k or prefix), r)
                    for k, r in _problems(exc)]
        raise ScenarioError(source, problems) from None


# --- pydantic errors -> (key, reason) ----------------------------------------------------------
_SECTIONS = {"backend": BackendConfig, "solver": SolverConfig, "material": MaterialConfig,
             "bond": BondConfig, "output": OutputConfig}
_EXPECTED = {"float_type": "a number", "int_type": "an integer", "int_from_float": "an integer",
             "string_type": "a string", "bool_type": "a boolean", "tuple_type": "an array",
             "list_type": "an array", "model_type": "a table", "dict_type": "a table",
             "model_attributes_type": "a table"}


def _toml_type(value) -> str:
    if isinstance(value, bool):
        return "a boolean"
    return {int: "an integer", float: "a float", str: "a string", tuple: "an array",
            list: "an array", dict: "a table"}.get(type(value), f"a {type(value).__name__}")


def _shown(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _key(loc) -> str:
    """('stage', 0, 'prepare', 'courses', 1) -> 'stage[1].courses[2]' (tags dropped)."""
    out = ""
    after_stage_index = False
    for item in loc:
        if isinstance(item, int):
            out += f"[{item + 1}]"
            after_stage_index = out.endswith("]") and out.rsplit("[", 1)[0] == "stage"
            continue
        if after_stage_index and item in STAGE_KINDS:    # discriminated-union tag in the path
            after_stage_index = False
            continue
        after_stage_index = False
        out = f"{out}.{item}" if out else str(item)
    return out


def _keys_at(loc) -> list[str]:
    """The keys allowed in the table at `loc` (for 'did you mean' hints)."""
    if not loc:
        model = Scenario
    elif len(loc) == 1 and loc[0] in _SECTIONS:
        model = _SECTIONS[loc[0]]
    elif len(loc) == 3 and loc[0] == "stage" and loc[2] in _STAGE_MODELS:
        model = _STAGE_MODELS[loc[2]]
    else:
        return []
    return [f.alias or name for name, f in model.model_fields.items()
            if name not in _LOADER_FIELDS]


def _unknown_key_reason(name, parent_loc) -> str:
    allowed = _keys_at(parent_loc)
    close = difflib.get_close_matches(str(name), allowed, n=1)
    if close:
        return f"unknown key (did you mean '{close[0]}'?)"
    return f"unknown key (expected one of: {', '.join(allowed)})" if allowed else "unknown key"


def _problems(exc: ValidationError) -> list[tuple[str, str]]:
    out = []
    errors = exc.errors()
    for err in errors:
        loc, kind, value = tuple(err["loc"]), err["type"], err.get("input")
        ctx = err.get("ctx") or {}
        key = _key(loc)
        if kind == "too_short" and any(len(e["loc"]) > len(loc) and tuple(e["loc"][:len(loc)])
                                       == loc for e in errors):
            continue    # pydantic counts only the items that validated: the items' errors say it
        if kind == "value_error" and isinstance(ctx.get("error"), _Problems):
            for sub, reason in ctx["error"].problems:
                out.append((f"{key}.{sub}" if key else sub, reason))
            continue
        if kind == "extra_forbidden":
            reason = _unknown_key_reason(loc[-1], loc[:-1])
        elif kind == "missing":
            reason = ("required value missing (at least one [[stage]] table)"
                      if loc == ("stage",) else "required value missing")
        elif kind == "union_tag_not_found":
            key, reason = f"{key}.kind", ("required value missing (the stage kind: "
                                          "'prepare' or 'shear')")
        elif kind == "union_tag_invalid":
            key, reason = f"{key}.kind", (f"unknown stage kind {ctx.get('tag')!r} (expected "
                                          f"'prepare' or 'shear')")
        elif loc == ("stage",) and kind == "tuple_type":
            reason = (f"wrong type: expected an array of tables ([[stage]]), got "
                      f"{_toml_type(value)}")
        elif kind in _EXPECTED:
            reason = (f"wrong type: expected {_EXPECTED[kind]}, got {_toml_type(value)} "
                      f"{_shown(value)}")
        elif kind == "string_pattern_mismatch":
            reason = (f"must contain only letters, digits, '_', '.' and '-', got "
                      f"{_shown(value)}")
        elif kind == "too_short":
            reason = "must not be empty"
        elif kind == "too_long":
            reason = f"must have at most {ctx.get('max_length')} items, got {len(value)}"
        elif kind == "value_error":
            reason = str(ctx.get("error", err["msg"]))
        else:    # bounds, literals, finiteness: pydantic's wording, with the value
            reason = f"{err['msg'].replace('Input should be', 'must be')}, got {_shown(value)}"
        out.append((key, reason))
    return out
