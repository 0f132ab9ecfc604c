"""Kinematic walls: planes and inner surfaces of finite cylinders with imposed motion.

A wall never feels the particles: its position is a function of time (fixed, constant velocity
or sinusoidal displacement about a point moving at constant velocity). The solver uses, over a step [t, t+H],
the wall velocity (p(t+H) - p(t)) / H, so that integrating it reproduces the prescribed
position exactly. The impulse particles exert on each wall is accumulated per step: that is the
wall force (impulse / H).

Geometry conventions (SI units):
- plane: `point` on the plane, `direction` the unit normal pointing INTO the granular domain;
  `radius` is only the size of the plate drawn by the renderer.
- cylinder: `point` on the axis, `direction` the unit axis, `radius` the inner radius,
  `extent` = (lo, hi) the axial range of the shell relative to `point`. A sphere whose centre's
  axial coordinate s lies within [lo, hi] touches the shell along the radius. Beyond its ends,
  `edges` says what the shell is there:
  - "rim" (the default): nothing but its rim, the circle of the inner radius at lo (or hi); the
    sphere touches it where its distance to that circle is below r, along the line from its
    centre to the circle's nearest point (a ring of the Leutner box ends at its rim);
  - "extended": the shell reaches r beyond each end, with the radial gap and normal (the
    geometry of sessions 1-31: the calibration scenarios keep it, `ring_edges`, so that
    their results stay reproducible (the study's scenarios use "rim" since session 32); it adds a phantom wall of up to one grain radius on
    either side of the shear box's gap).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Tuple

import numpy as np

PLANE, CYLINDER = 0, 1
KINDS = {"plane": PLANE, "cylinder": CYLINDER}
MOTIONS = ("fixed", "constant", "sine")
EDGES = ("rim", "extended")

Vec = Tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class Wall:
    """A rigid kinematic wall.

    kind: "plane" or "cylinder". point (m), direction (unit), radius (m), extent (m, cylinder
    axial range). motion: "fixed", "constant" (velocity, m/s) or "sine" (displacement
    velocity * s + amplitude * sin(2 pi frequency s), s = t - start), amplitude in m,
    frequency in Hz. start (s) is
    when the motion begins (the wall rests at `point` before). friction: Coulomb coefficient
    against particles. system: in a batch of independent systems (Simulation.batch), the one
    whose particles the wall touches; -1 (default): every particle. edges: a cylinder's ends,
    "rim" or "extended" (module docstring).
    """
    kind: str
    point: Vec
    direction: Vec
    radius: float = 0.075
    extent: Tuple[float, float] = (0.0, 0.0)
    friction: float = 0.0
    motion: str = "fixed"
    velocity: Vec = (0.0, 0.0, 0.0)
    amplitude: Vec = (0.0, 0.0, 0.0)
    frequency: float = 0.0
    start: float = 0.0
    name: str = ""
    system: int = -1
    edges: str = "rim"

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"wall {self.name!r}: unknown kind {self.kind!r} (plane, cylinder)")
        if self.edges not in EDGES:
            raise ValueError(f"wall {self.name!r}: unknown edges {self.edges!r} {EDGES}")
        if self.motion not in MOTIONS:
            raise ValueError(f"wall {self.name!r}: unknown motion {self.motion!r} {MOTIONS}")
        for key in ("point", "direction", "velocity", "amplitude"):
            v = np.asarray(getattr(self, key), dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"wall {self.name!r}: {key} must be a finite 3-vector, got "
                                 f"{getattr(self, key)!r}")
            object.__setattr__(self, key, tuple(float(c) for c in v))
        for key in ("radius", "friction", "frequency", "start"):
            try:
                value = float(getattr(self, key))
            except (TypeError, ValueError):
                raise ValueError(f"wall {self.name!r}: {key} must be a number, got "
                                 f"{getattr(self, key)!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"wall {self.name!r}: {key} must be finite, got {value!r}")
            object.__setattr__(self, key, value)
        ext = np.asarray(self.extent, dtype=float)
        if ext.shape != (2,) or not np.all(np.isfinite(ext)):
            raise ValueError(f"wall {self.name!r}: extent must be two finite numbers (lo, hi), "
                             f"got {self.extent!r}")
        object.__setattr__(self, "extent", (float(ext[0]), float(ext[1])))
        d = np.asarray(self.direction, dtype=float)
        with np.errstate(over="ignore", under="ignore"):
            n = float(np.linalg.norm(d))
        if not 0 < n < math.inf:
            # a norm that overflows ((1e300, 1e300, 0)) or underflows: the vector scaled first
            # (only then: a rescaled vector normalises differently in the last bit)
            scale = float(np.max(np.abs(d))) if d.size else 0.0
            if not scale > 0:
                raise ValueError(f"wall {self.name!r}: direction must be a non-zero vector")
            d = d / scale
            n = float(np.linalg.norm(d))
        object.__setattr__(self, "direction", tuple(float(c) for c in d / n))
        if self.kind == "cylinder":
            if not self.radius > 0:
                raise ValueError(f"wall {self.name!r}: cylinder radius must be positive")
            if not self.extent[1] > self.extent[0]:
                raise ValueError(f"wall {self.name!r}: cylinder extent must have hi > lo")
        if self.friction < 0:
            raise ValueError(f"wall {self.name!r}: friction must be >= 0")
        if self.radius < 0:
            raise ValueError(f"wall {self.name!r}: radius must be >= 0, got {self.radius!r}")
        if isinstance(self.system, (bool, np.bool_)) or not isinstance(self.system, (int, np.integer)) \
                or self.system < -1:
            raise ValueError(f"wall {self.name!r}: system must be an integer >= -1, got {self.system!r}")
        object.__setattr__(self, "system", int(self.system))
        if self.motion == "sine" and not self.frequency > 0:
            raise ValueError(f"wall {self.name!r}: sinusoidal motion needs frequency > 0")
        unused = [key for key, motions in (("velocity", ("constant", "sine")),
                                           ("amplitude", ("sine",)))
                  if self.motion not in motions and any(getattr(self, key))]
        if self.motion != "sine" and self.frequency:
            unused.append("frequency")
        if unused:
            import warnings
            from .stack import user_stacklevel
            warnings.warn(f"wall {self.name!r}: motion {self.motion!r} ignores its "
                          f"{' and '.join(unused)} (give motion=\"constant\" or \"sine\"; to "
                          "set a moving wall going from where it is, Wall.moving_from)",
                          UserWarning, stacklevel=user_stacklevel())

    def position(self, t: float) -> np.ndarray:
        p0 = np.asarray(self.point, dtype=float)
        s = t - self.start
        if self.motion == "fixed" or s <= 0:
            return p0
        drift = p0 + np.asarray(self.velocity, dtype=float) * s
        if self.motion == "constant":
            return drift
        return drift + np.asarray(self.amplitude, dtype=float) * math.sin(2 * math.pi * self.frequency * s)

    def step_velocity(self, t: float, h: float) -> np.ndarray:
        return (self.position(t + h) - self.position(t)) / h

    def moved(self, **changes) -> "Wall":
        """A copy with `changes` (dataclasses.replace): the motion keeps its anchor (`point`
        at `start`), so a new velocity alone makes the wall jump to where it would have been;
        `moving_from` sets a wall going from where it is."""
        return dataclasses.replace(self, **changes)

    def moving_from(self, t: float, velocity) -> "Wall":
        """This wall moving at the constant `velocity` (m/s) from time `t` on, from where it is
        at `t`: for `Simulation.replace_wall(k, wall.moving_from(sim.time, v))`, which keeps
        its contact history (as the preparation's servo plate is driven)."""
        return dataclasses.replace(self, point=tuple(self.position(t)), motion="constant",
                                   velocity=tuple(velocity), amplitude=(0.0, 0.0, 0.0),
                                   frequency=0.0, start=float(t))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Wall":
        """A wall from `to_dict`'s dict. A cylinder written before walls had `edges` (tcd
        before session 31's last commits) keeps the geometry it ran with: "extended"."""
        d = dict(d)
        d.setdefault("edges", "extended")
        for key in ("point", "direction", "velocity", "amplitude", "extent"):
            if key in d:
                d[key] = tuple(d[key])
        return cls(**d)


def plane(point, normal, **kw) -> Wall:
    return Wall("plane", tuple(point), tuple(normal), **kw)


def cylinder(point, axis, radius, extent, **kw) -> Wall:
    return Wall("cylinder", tuple(point), tuple(axis), radius=radius, extent=tuple(extent), **kw)
