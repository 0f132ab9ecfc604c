"""Preparation (pour, vibrate, confine) and Leutner shear as sequences of phases.

A protocol turns one scenario stage into phases, planned one at a time from the simulation
state at the start of each phase (`plan(index, sim)`), so a run can be checkpointed anywhere
and resumed: a phase is plain data (walls, step budget, settle rule) stored in the checkpoint.

Preparation (PHYSICS.md section 7), for each course from the bottom up:
  pour    : the course's spheres at random sites of a cubic lattice (seeded, with a small
            random horizontal offset of each site to break the lattice symmetry) above the bed,
            falling into the frictionless mould until settled: after the free-fall time of the
            column, the run stops at the first check (every 50 steps) where the kinetic energy
            is negligible: the mass-weighted rms speed sqrt(2 KE / M) is below `settle_speed`
            (0.005 m/s: KE per unit mass below 1.3e-5 J/kg, against ~8 J/kg of potential
            energy released by a 1.6 m column), or at `max_settle_time`. (The fastest sphere
            is not the criterion: a few rattlers in the cages of the bed keep ~1 cm/s for
            seconds while the bed as a whole is at rest);
  vibrate : a top plate placed on the bed oscillates vertically (amplitude, frequency,
            duration) while its mean position descends toward the layer's target height;
  hold    : the plate descends to the target height and holds there until settled.
Then `confine`: top plate to the sample height, settle. The sample is saved for the shear.

The top plate is a servo-controlled kinematic wall: rigid spheres jammed above the target
cannot be pushed lower by a plate whose motion is imposed blindly (the contact problem has no
solution and the solver would leave overlaps, or squeeze grains through the mould). Each step
the plate follows its prescribed motion, at most at the prescribed peak speed, except that
while the particles push on it with more than `force_limit` (a multiple of the weight of the
sample) it backs off by one step of that speed. (Session 16: a plate that only stopped
ratcheted into a jammed bed, one step down whenever the push had dropped, each step leaving
overlaps that no projection can remove under a plate that never rises, and a locked-in force
of hundreds of times the weight: the scaled twin ended with overlaps of 1.2 to 3.6 % of the
smallest diameter in three seeds of five.) The final heights are then measured, not assumed.
On a bed jammed above its target (the scaled twin; the full-size samples end below theirs) the
plate then dithers, one step into the bed and one back, and those steps stop at the sweep cap.
A plate that stayed where it first backed off made them converge but kept the vibration's
overlaps (up to 4 % of the smallest diameter, against below 1 %): the dithering lets the
position projection remove them (docs/measurements.md, session 19).

Leutner shear (section 8): bond every particle contact, replace the mould by two rings with a
gap at the layer interface, move the upper ring and the top plate horizontally at constant
velocity; record per step the reaction of the particles on the upper ring.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import observables as obs
from . import packing
from .walls import Wall, cylinder, plane

# the prepare series' `phase` column: index in this tuple (its attribute `phase_names`)
PREPARE_PHASES = ("pour", "vibrate", "hold", "confine")
SETTLE_CHECK_EVERY = 50


@dataclasses.dataclass
class Phase:
    """One phase of a stage: walls, step budget and stopping rule (plain data, JSON-able)."""
    name: str
    walls: list
    steps: int
    settle: bool = False
    min_steps: int = 0
    info: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["walls"] = [w.to_dict() for w in self.walls]
        return d

    @classmethod
    def from_json(cls, d: dict) -> "Phase":
        d = dict(d)
        d["walls"] = [Wall.from_dict(w) for w in d["walls"]]
        return cls(**d)


def servo_step(sim, phase) -> None:
    """Move the servo plate for the coming step (see module docstring)."""
    sv = phase.info.get("servo")
    if not sv:
        return
    t, h = sim.time, sim.settings.time_step
    s = t + h - sv["t0"]
    mean = max(sv["target"], sv["z0"] + sv["v_mean"] * s)
    z_p = mean + sv["amplitude"] * math.sin(2 * math.pi * sv["frequency"] * s)
    z = sv["z"]
    dz = min(max(z_p - z, -sv["v_max"] * h), sv["v_max"] * h)
    push = float(sim.wall_force(sv["wall"])[2]) if sim.step_index > 0 else 0.0
    if push > sv["force_limit"]:
        dz = sv["v_max"] * h            # back off: never hold a jammed bed below its height
    plate = sim.walls[sv["wall"]]
    sim.replace_wall(sv["wall"], plate.moved(point=(0.0, 0.0, z), motion="constant",
                                             velocity=(0.0, 0.0, dz / h), start=t))
    sv["z"] = z + dz


def settled(sim, speed: float) -> bool:
    """Kinetic energy negligible: mass-weighted rms speed sqrt(2 KE / M) below `speed`."""
    v, r = sim.velocities(), sim.radii()
    m = r**3
    return float(np.sqrt((m * (v**2).sum(axis=1)).sum() / m.sum())) < speed


#: the largest overlap a prepared sample may keep, over its smallest diameter (issue 5: 1 %)
MAX_SAMPLE_OVERLAP = 0.01

#: the largest kinetic energy of a quasi-static shear, over the walls' work (the study's: 6.3e-5
#: to 1.7e-4; the twin's below 1e-3): above it the summary warns of flung grains
QUASI_STATIC_KINETIC_RATIO = 0.01

#: how far a sheared sample may turn about the mould's axis before the peak, as the distance
#: its rim moved over the ring's travel, before the summary warns (session 48: the study,
#: rings of friction 0.3, 0.004-0.012; `tiny.toml` with frictionless rings 23, spinning up
#: exponentially, and with friction 0.3, 0.08)
TURN_RIM_OVER_RING = 1.0


#: how far below its target `packing_fraction` a prepared sample may pack before its summary
#: warns (the study's samples: 0.584-0.591 for 0.587; the twin 0.579)
LOOSE_PACKING = 0.05


class Prepare:
    """Two-course (or more) sample by pouring and vibration."""
    kind = "prepare"

    def __init__(self, stage, scenario, seed: int):
        self.cfg, self.scn, self.seed = stage, scenario, seed
        self.radius = stage.cylinder_diameter_mm * 5e-4
        self.h = scenario.solver.time_step

    # -- sizes ---------------------------------------------------------------------------------
    def layer_radii(self, layer: int) -> np.ndarray:
        course = self.cfg.courses[layer]
        rng = np.random.default_rng([self.seed, layer, 0])
        return packing.course_radii(course, self.cfg.layer_particle_count(course), rng) * self.cfg.size_scale

    def column_top(self) -> float:
        return self.cfg.column_height_mm * 1e-3

    def mould(self) -> list:
        R, f = self.radius, self.scn.material.wall_friction
        top = self.column_top() + 0.05
        return [plane((0, 0, 0), (0, 0, 1), radius=R, friction=f, name="bottom plate"),
                cylinder((0, 0, 0), (0, 0, 1), R, (0.0, top), friction=f, name="mould")]

    def steps(self, seconds: float) -> int:
        return max(1, int(round(seconds / self.h)))

    # -- phases --------------------------------------------------------------------------------
    def phase_names(self):
        names = []
        for L in range(len(self.cfg.courses)):
            names += [("pour", L), ("vibrate", L), ("hold", L)]
        return names + [("confine", len(self.cfg.courses) - 1)]

    def plan(self, index: int, sim, t: float):
        """Phase `index` planned from the current simulation (may return a new one)."""
        names = self.phase_names()
        if index >= len(names):
            return None, sim
        name, L = names[index]
        c = self.cfg
        if name == "pour":
            sim = self._add_layer(sim, L, t)
            top = float((sim.positions()[:, 2] + sim.radii()).max())
            fall = math.sqrt(2.0 * top / max(self.scn.solver.gravity, 1e-9))
            return Phase("pour", self.mould(), self.steps(c.max_settle_time), settle=True,
                         min_steps=self.steps(fall), info={"layer": L}), sim
        target = (L + 1) * c.layer_height_mm * 1e-3
        if name == "confine":
            target = c.sample_height_mm * 1e-3
        x, r = sim.positions(), sim.radii()
        bed = float((x[:, 2] + r).max())
        weight = float(np.sum(self.scn.material.density * 4 / 3 * math.pi * r**3)) * self.scn.solver.gravity
        start = bed + 1e-4 if name == "vibrate" else (sim.walls[2].position(t)[2] if len(sim.walls) > 2 else bed + 1e-4)
        amp = c.vibration_amplitude_mm * 1e-3 if name == "vibrate" else 0.0
        dur = max(c.vibration_duration, self.h)
        servo = {"wall": 2, "z": start, "z0": start, "target": target, "t0": t,
                 "amplitude": amp, "frequency": c.vibration_frequency,
                 "force_limit": c.plate_force_factor * max(weight, 1e-12)}
        if name == "vibrate":
            servo["v_mean"] = (target - start) / dur
            servo["v_max"] = max(2 * math.pi * c.vibration_frequency * amp + abs(servo["v_mean"]), 1e-3)
            steps, settle = self.steps(c.vibration_duration), False
        else:
            # approach the target slower than the settling speed, so the plate's own motion
            # never keeps the bed from being declared settled
            servo["v_mean"] = servo["v_max"] = 0.5 * c.settle_speed
            servo["v_mean"] *= -1.0
            steps, settle = self.steps(c.max_hold_time), True
        top = plane((0, 0, start), (0, 0, -1), radius=self.radius,
                    friction=self.scn.material.wall_friction, name="top plate")
        return Phase(name, self.mould() + [top], steps, settle=settle,
                     min_steps=self.steps(0.05) if settle else 0,
                     info={"layer": L, "target": target, "servo": servo}), sim

    def before_step(self, sim, phase) -> None:
        servo_step(sim, phase)

    def _add_layer(self, sim, L: int, t: float):
        c = self.cfg
        r_new = self.layer_radii(L)
        rng = np.random.default_rng([self.seed, L, 1])
        if sim is None:
            base, old = 0.0, None
        else:
            old = sim.state_dict()
            base = float((old["particles/x"][:, 2] + old["particles/radius"]).max())
        x_new = packing.lattice_column(r_new, 2 * self.radius, base + 1e-3, rng,
                                       max_height=self.column_top() - base,
                                       jitter=c.lattice_jitter_mm * 1e-3)
        layer_new = np.full(len(r_new), L, np.int32)
        if old is None:
            r, x, v, w, layer = r_new, x_new, None, None, layer_new
        else:
            r = np.concatenate([old["particles/radius"], r_new])
            x = np.concatenate([old["particles/x"], x_new])
            v = np.concatenate([old["particles/v"], np.zeros_like(x_new)])
            w = np.concatenate([old["particles/w"], np.zeros_like(x_new)])
            layer = np.concatenate([old["particles/layer"], layer_new])
        new = make_simulation(self.scn, r, x, layer, self.mould(), t, self.radius,
                              self.column_top() + 0.05)
        if v is not None:
            new.set_velocities(v)
            new.set_angular_velocities(w)
        if sim is not None:
            sim.close()
        return new

    # -- records -------------------------------------------------------------------------------
    def phase_end(self, sim, phase) -> dict:
        """Numbers kept with the record of a phase that has just ended: at the end of a
        course's hold, the course as built (its grains' 99th-percentile top, its highest
        grain's top and the plate)."""
        if phase.name != "hold":
            return {}
        L = int(phase.info["layer"])          # courses 0..L are in the mould
        x, r, layer = sim.positions(), sim.radii(), sim.state_dict()["particles/layer"]
        tops = obs.layer_tops(x, r, layer)
        return {"course_top_mm": 1e3 * tops[L],
                "course_highest_top_mm": 1e3 * obs.layer_highest(x, r, layer)[L],
                "plate_mm": 1e3 * float(sim.walls[2].position(sim.time)[2])}

    def record(self, sim, phase, motion=None) -> dict:
        """The series row of a preparation step (`motion`, the shear's, is not needed)."""
        row = {"phase": PREPARE_PHASES.index(phase.name),
               "layer": phase.info.get("layer", 0)}
        if len(sim.walls) > 2:
            row["top_plate_force"] = float(sim.wall_force(2)[2])
            row["top_plate_z"] = float(sim.walls[2].position(sim.time)[2])
        else:
            row["top_plate_force"] = 0.0
            row["top_plate_z"] = float("nan")
        return row

    @staticmethod
    def as_built(phases, courses: int, key: str = "course_top_mm") -> list:
        """Each course's height as built (mm): its top when its own hold ended, from the top of
        the course below at the end of that one's hold (the first from the bottom plate).
        `phases` are the stage's phase records (runner: result["phases"]); `key` the top read
        (`course_top_mm`, the 99th percentile of the grain tops; `course_highest_top_mm`, the
        highest grain: where a plate lowered onto the course rests); None for a course whose
        record lacks it (a run resumed from a checkpoint older than the record)."""
        tops = [None] * courses
        for rec in phases or ():
            if rec.get("phase") == "hold" and key in rec:
                tops[int(rec["layer"])] = float(rec[key])
        below = [0.0] + tops[:-1]
        return [None if t is None or b is None else t - b for t, b in zip(tops, below)]

    def finish(self, sim, phases=()) -> dict:
        """The prepared sample's numbers; `phases`: the stage's phase records (for the
        heights as built)."""
        x, r, layer = sim.positions(), sim.radii(), sim.state_dict()["particles/layer"]
        H = float(sim.walls[2].position(sim.time)[2]) if len(sim.walls) > 2 else self.cfg.sample_height_mm * 1e-3
        tops = obs.layer_tops(x, r, layer)
        highest = [0.0] + obs.layer_highest(x, r, layer)
        top = max(highest)                        # the sample's highest grain
        nl = len(tops)
        area = math.pi * self.radius**2
        vol = 4.0 / 3.0 * math.pi * r**3
        # layers are slabs between the plates and the equal-volume interfaces, so that the
        # heights add up to the sample height and the per-layer packing fractions (all sphere
        # volume inside each slab) average to the overall one
        bounds = [0.0] + [obs.layer_interface(x, r, layer, L, L + 1) for L in range(nl - 1)] + [H]
        # diagnostics of the interface: each course's lift from the top of the course below
        # (99th percentile of grain tops) to its own top (the last one to the top plate), with
        # its own grains' volume over that lift; and the upper course's grains that fell into
        # the pores of the course below (centre below its top), with the depth of the deepest
        lifts = [0.0] + tops[:-1] + [H]
        c = sim.contact_arrays()
        out = {
            "particles": int(sim.n),
            "particles_per_layer": [int(np.count_nonzero(layer == L)) for L in range(nl)],
            "layer_tops_mm": [1e3 * t for t in tops],
            "layer_interfaces_mm": [1e3 * b for b in bounds[1:-1]],
            "layer_heights_mm": [1e3 * (bounds[k + 1] - bounds[k]) for k in range(nl)],
            "packing_fraction_per_layer": [obs.packing_fraction(x, r, self.radius, bounds[L], bounds[L + 1])
                                           for L in range(nl)],
            "course_heights_as_built_mm": self.as_built(phases, nl),
            "course_heights_as_built_by_highest_grain_mm": self.as_built(phases, nl,
                                                                         "course_highest_top_mm"),
            # the finished sample read the same way: each course from the highest grain of the
            # course below to its own highest grain (where a plate lowered onto it would rest)
            "course_heights_by_highest_grain_mm": [1e3 * (highest[k + 1] - highest[k]) for k in range(nl)],
            "course_lift_heights_mm": [1e3 * (lifts[k + 1] - lifts[k]) for k in range(nl)],
            "course_packing_fraction_per_lift": [float(vol[layer == L].sum()) / (area * (lifts[L + 1] - lifts[L]))
                                                 for L in range(nl)],
            "grains_in_lower_course": [0] + [int(np.count_nonzero((layer == L) & (x[:, 2] < tops[L - 1])))
                                             for L in range(1, nl)],
            "deepest_grain_below_lower_top_mm": [0.0] + [
                1e3 * max(0.0, tops[L - 1] - float(x[layer == L, 2].min())) if np.any(layer == L) else 0.0
                for L in range(1, nl)],
            "packing_fraction": obs.packing_fraction(x, r, self.radius, 0.0, H),
            # pairs within the alert distance per particle (what sessions 1-41 reported), and
            # the contacts that carried a force over the last step (granular mechanics' Z)
            "coordination_number": obs.coordination_number(c["i"], c["j"], sim.n),
            "coordination_number_force_carrying": obs.coordination_number(
                c["i"], c["j"], sim.n, obs.carries_force(c["i"], c["j"], c["impulse"], x)),
            "max_overlap_ratio": obs.max_overlap(c["gap"]) / (2 * float(r.min())),
            # a sphere is outside when it pokes through a wall by more than 1 % of d_min
            "outside": obs.outside(x, r, self.radius, 0.0, H),
            "sample_height_mm": 1e3 * H,
            # the grains' own top: where a plate lowered onto the finished sample would rest
            # (the shear stage rests its plate there), its gap to the top plate, and the
            # packing over that height (the full-size samples end below their plate)
            "highest_grain_top_mm": 1e3 * top,
            "top_plate_gap_mm": 1e3 * (H - top),
            "packing_fraction_below_highest_grain": obs.packing_fraction(x, r, self.radius, 0.0,
                                                                         min(top, H)),
            "target_sample_height_mm": self.cfg.sample_height_mm,
            "diameter_mm": 2e3 * self.radius,
        }
        out["warnings"] = self.shortfalls(phases, 1e3 * H, out["max_overlap_ratio"], out["outside"],
                                          out["packing_fraction"], 1e3 * top)
        return out

    def shortfalls(self, phases, height_mm: float, overlap_ratio: float = 0.0,
                   outside: int = 0, packing: float | None = None,
                   top_mm: float | None = None) -> list:
        """Where the preparation fell short of what its scenario asked (a list of sentences,
        empty when nothing did): a pour, hold or confinement that reached its time limit before
        the grains settled (`settle_speed`), a course whose plate stopped above its target (the
        grains jammed: the course is taller than `layer_height_mm`), a sample taller than
        `sample_height_mm`, a sample packed well below `packing_fraction` (too few grains for
        its layers: they settle under the plate). Each one is printed when the stage ends and
        kept in summary.json."""
        c, out = self.cfg, []
        slack = 0.01 * c.layer_height_mm
        for rec in phases or ():
            name, L = rec.get("phase"), rec.get("layer", 0)
            if rec.get("settled") is False:
                out.append(f"{name} of course {L} ({c.courses[int(L)]}) reached its time limit "
                           f"({rec.get('steps')} steps) before the grains settled below "
                           f"{c.settle_speed:g} m/s")
            if name == "hold" and "plate_mm" in rec and "target" in rec:
                target = 1e3 * float(rec["target"])
                if float(rec["plate_mm"]) > target + slack:
                    out.append(f"course {L} ({c.courses[int(L)]}): its plate stopped at "
                               f"{float(rec['plate_mm']):.2f} mm, above its target {target:.2f} "
                               "mm: the grains jammed above it")
        if height_mm > c.sample_height_mm + slack:
            out.append(f"the sample is {height_mm:.2f} mm high, above sample_height_mm "
                       f"({c.sample_height_mm:g} mm)")
        # the invariants of a prepared sample (issue 5): a run that diverged breaks them first
        if not overlap_ratio <= MAX_SAMPLE_OVERLAP:
            out.append(f"the largest overlap is {100 * overlap_ratio:.3g} % of the smallest "
                       f"diameter, above {100 * MAX_SAMPLE_OVERLAP:g} %: the grains interpenetrate "
                       "(a time step or gravity too large for the solver's tolerance?)")
        if outside:
            out.append(f"{outside} grain(s) ended outside the mould")
        if packing is not None and packing < c.packing_fraction - LOOSE_PACKING:
            under = (f"; its highest grain reaches {top_mm:.2f} mm under the plate at "
                     f"{height_mm:.2f} mm" if top_mm is not None else "")
            out.append(f"the sample's packing fraction is {packing:.3f}, well below "
                       f"packing_fraction {c.packing_fraction:g}{under}: its grains do not fill "
                       "its layers (particles_per_layer too small for the mould and layer "
                       "height?), and a shear of it tests a loose bed")
        return out


class Shear:
    """Leutner shear test on a prepared sample."""
    kind = "shear"

    def __init__(self, stage, scenario, seed: int):
        self.cfg, self.scn, self.seed = stage, scenario, seed
        self.h = scenario.solver.time_step
        self.velocity = stage.velocity_mm_per_min * 1e-3 / 60.0
        self.displacement = stage.displacement_mm * 1e-3

    def plan(self, index: int, sim, t: float):
        if index > 0:
            return None, sim
        if sim is None:
            raise ValueError("the shear stage needs a prepared sample (a prepare stage before it, "
                             "or `sample = \"path/to/prepared.h5\"`)")
        c = self.cfg
        x, r = sim.positions(), sim.radii()
        R, plate, H, problems = self.sample_geometry(sim.walls, x, r, t)
        if problems:
            raise ValueError("; ".join(problems))
        z_i = 0.5 * H
        half_gap = 0.5 * c.gap_mm * 1e-3
        f = c.wall_friction
        v = (self.velocity, 0.0, 0.0)
        walls = [
            plane((0, 0, 0), (0, 0, 1), radius=R, friction=f, name="bottom plate"),
            # each ring reaches at least its plate: a sample taller than two rings has no hole
            cylinder((0, 0, 0), (0, 0, 1), R, (min(z_i - c.ring_height_mm * 1e-3, 0.0), z_i - half_gap),
                     friction=f, name="lower ring", edges=c.ring_edges),
            cylinder((0, 0, 0), (0, 0, 1), R, (z_i + half_gap, max(z_i + c.ring_height_mm * 1e-3, H)),
                     friction=f, motion="constant", velocity=v, start=t, name="upper ring",
                     edges=c.ring_edges),
            plane((0, 0, H), (0, 0, -1), radius=R, friction=f, motion="constant", velocity=v,
                  start=t, name="top plate"),
        ]
        if c.renumber:
            # along the shear: neighbours close in memory, slabs of contiguous particles
            old, sim = sim, sim.renumber(np.argsort(x[:, 0], kind="stable"))
            old.close()
        bond_law = self.scn.bond.to_law(c.bond_mode)
        sim.bond_law = bond_law
        sim.set_walls(walls)
        nb = sim.create_bonds(self.scn.bond.gap_tolerance_mm * 1e-3)
        steps = int(round(self.displacement / self.velocity / self.h))
        return Phase("shear", walls, steps, info={"z_interface": z_i, "radius": R, "t0": t,
                                                  "bonds_created": nb, "sample_height": H,
                                                  "mould_height": plate}), sim

    def sample_geometry(self, walls, x, r, t: float):
        """(mould radius R, top plate height, sample height H, problems) of a prepared sample
        with these walls and grains at time `t`: what `plan` needs of a sample, checked before
        a run starts (runner.check_samples) as well as here. The sample is confined: the top
        plate rests on its highest grain (vibration may have packed the grains below the
        mould's height; a gap would let the bonded sample jump)."""
        c = self.cfg
        moulds = [w.radius for w in walls if w.kind == "cylinder"]
        plates = [w.position(t)[2] for w in walls if w.kind == "plane" and w.direction[2] < 0]
        problems = []
        if not moulds:
            problems.append("the sample has no cylindrical mould among its walls (the rings take "
                            "its radius)")
        if not plates:
            problems.append("the sample has no top plate (a plane facing down) among its walls")
        if problems:
            return math.nan, math.nan, math.nan, problems
        R, plate = float(max(moulds)), float(max(plates))
        H = min(plate, float((x[:, 2] + r).max()))
        if self.displacement >= 2 * R:
            problems.append(f"shear displacement_mm {c.displacement_mm:g} mm is not smaller than "
                            f"the sample's {2e3 * R:g} mm diameter: the upper ring would leave "
                            "the lower one")
        return R, plate, H, problems

    def before_step(self, sim, phase) -> None:
        # the stage's solver settings (here, not in plan: a resumed run passes here too)
        c = self.cfg
        changes = {k: v for k, v in (("tolerance", c.tolerance), ("max_sweeps", c.max_sweeps))
                   if v is not None and getattr(sim.settings, k) != v}
        if changes:
            sim.settings = dataclasses.replace(sim.settings, **changes)

    def record(self, sim, phase, motion=None) -> dict:
        """The series row of a shear step; `motion`: the grains' (velocities, angular
        velocities) when the caller has read them already (else they are read here)."""
        R = phase.info["radius"]
        f_ring = sim.wall_force(2)
        d = sim.bonds_state_counts()
        return {"displacement": self.velocity * (sim.time - phase.info["t0"]),
                "shear_force": float(-f_ring[0]),
                "top_plate_shear_force": float(-sim.wall_force(3)[0]),
                "shear_stress": float(-f_ring[0] / (math.pi * R**2)),
                "bonds_intact": d[0], "bonds_broken_tension": d[1], "bonds_broken_shear": d[2],
                # the sample's turn about the mould's axis (free with frictionless rings)
                "spin": obs.spin_about_axis(sim.positions(), *(motion or (
                    sim.velocities(), sim.angular_velocities())), *sim.inverse_masses())}

    def finish(self, sim, phase, series: dict, x_start=None) -> dict:
        """Peak, residual and bond counts; with `x_start` (positions at the start of the shear)
        also how far the grains of each half moved along the shear, over the ring's travel.

        Near the plane means within a quarter of the ring height of the interface; the share of
        all bonds in that band is reported next to the share of broken ones (bonds break mostly
        near the plane when the second clearly exceeds the first). A bond's height is the
        middle of its gap (`observables.bond_gap_middle`): now for an intact bond, when it broke
        for a broken one (session 47; before, an intact bond sat at its centres' midpoint)."""
        c = self.cfg
        d = np.asarray(series["displacement"])
        s = np.asarray(series["shear_stress"])
        tau, d_peak, k = obs.peak_of(d, s, c.smoothing_window_mm * 1e-3)
        tail = obs.smooth(s, d, c.smoothing_window_mm * 1e-3)[-1]
        st = sim.state_dict()
        state = st["bonds/state"]
        broken = state != 0
        z_i = phase.info["z_interface"]
        band = 0.25 * c.ring_height_mm * 1e-3
        x = sim.positions()
        if len(state):
            # a bond's height: the middle of its gap, now (intact) or when it broke (the point
            # the solver records as broken_pos), so that both are measured alike
            z_b = np.where(broken, st["bonds/broken_pos"][:, 2],
                           obs.bond_gap_middle(x, sim.radii(), st["bonds/i"], st["bonds/j"])[:, 2])
            near = np.abs(z_b - z_i) < band
        else:
            near = np.zeros(0, bool)
        # energy: work of the moving walls on the grains (ring and top plate, both along x)
        # against the kinetic energy; a quasi-static test keeps the ratio small
        work = 0.0
        if "top_plate_shear_force" in series and len(d) > 1:
            f = np.asarray(series["shear_force"]) + np.asarray(series["top_plate_shear_force"])
            work = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(d)))
        ke = np.asarray(series.get("kinetic_energy", []), dtype=float)
        ke_max = float(np.nanmax(ke)) if len(ke) else float("nan")
        out = {
            "wall_work_J": work, "kinetic_energy_max_J": ke_max,
            "kinetic_over_work_max": ke_max / work if work > 0 else float("nan"),
            "tau_peak_MPa": tau * 1e-6, "d_peak_mm": d_peak * 1e3, "residual_MPa": float(tail) * 1e-6,
            "peak_index": k, "smoothing_window_mm": c.smoothing_window_mm,
            "peak_at_end": obs.peak_at_end(d, d_peak, c.smoothing_window_mm * 1e-3),
            "bonds_total": int(len(broken)), "bonds_broken": int(broken.sum()),
            "bonds_broken_tension": int(np.count_nonzero(state == 1)),
            "bonds_broken_shear": int(np.count_nonzero(state == 2)),
            "mould_diameter_mm": 2e3 * phase.info["radius"],
            "sample_height_mm": phase.info.get("sample_height", 2 * z_i) * 1e3,
            "z_interface_mm": z_i * 1e3, "near_plane_band_mm": band * 1e3,
            "bonds_near_plane_fraction": float(near.mean()) if len(near) else 0.0,
            "broken_near_plane_fraction": float(near[broken].mean()) if broken.any() else 0.0,
            "particles": int(sim.n),
        }
        warnings = []
        if "spin" in series and "time" in series and len(d):
            # up to the peak: after it a brittle cascade may fling pieces of the sample
            R = phase.info["radius"]
            spin = np.asarray(series["spin"], dtype=float)[:k + 1]
            t = np.asarray(series["time"], dtype=float)[:k + 1]
            out["spin_rim_over_ring_max"] = float(np.max(np.abs(spin))) * R / self.velocity
            # how far the rim turned (the spin integrated by trapezoids) over how far the ring
            # moved: the instantaneous spin has brief spikes as bonds break (the study's: up
            # to 7 ring speeds by the peak), the turn they make is small (0.4-1.2 % of the
            # ring's travel)
            turn = np.concatenate([[0.0], np.cumsum(0.5 * (spin[1:] + spin[:-1]) * np.diff(t))])
            travel = max(float(d[k]), float(d[-1]), 1e-300)
            out["turn_rim_over_ring"] = float(np.max(np.abs(turn))) * R / travel
            rim = out["turn_rim_over_ring"]
            if rim > TURN_RIM_OVER_RING:
                warnings.append(
                    f"the sample turned about the mould's axis before the peak: its rim moved "
                    f"{rim:.3g} times as far as the ring (a quasi-static test stays far below "
                    f"{TURN_RIM_OVER_RING:g}; its rim turned up to "
                    f"{out['spin_rim_over_ring_max']:.3g} times as fast as the ring moves). "
                    "Nothing holds that turn but the rings' and plates' friction, and the "
                    "ring's push about its offset axis drives it (docs/physics.md, the last "
                    "section): give the shear stage a wall_friction (the study's is 0.3), or "
                    "shear slower; the stress of such a test is not the Leutner test's")
        ratio = out["kinetic_over_work_max"]
        if ratio > QUASI_STATIC_KINETIC_RATIO:
            warnings += [
                f"the grains' kinetic energy reached {ratio:.3g} of the walls' work (a "
                f"quasi-static shear stays below {QUASI_STATIC_KINETIC_RATIO:g}): the drive is "
                "fast for this sample, the sample had not settled, or grains were flung (a "
                "bonded grain free to roll needs F H^2 / (m L) below 5.6: docs/physics.md, "
                "limitations)"]
        if warnings:
            out["warnings"] = warnings
        # grains squeezed out between the rings (a gap wider than the smallest grains: the
        # user audit of session 48 found 0.8 mm grains 1.4 mm out of a mould, nothing said)
        R, travel = phase.info["radius"], self.velocity * (sim.time - phase.info["t0"])
        r = sim.radii()
        rho = np.where(x[:, 2] > z_i, np.hypot(x[:, 0] - travel, x[:, 1]), np.hypot(x[:, 0], x[:, 1]))
        out["outside"] = int(np.count_nonzero(rho > R))
        if out["outside"]:
            warnings.append(f"{out['outside']} grain(s) ended outside the rings (their centres "
                            f"beyond the {1e3 * R:g} mm radius), squeezed out between them: the "
                            f"gap is {c.gap_mm:g} mm, the smallest grains "
                            f"{2e3 * float(np.min(r)):.3g} mm across (keep gap_mm below it)")
            out["warnings"] = warnings
        if x_start is not None:
            z0 = x_start[:, 2]
            dx = x[:, 0] - x_start[:, 0]
            upper, lower = z0 > z_i + band, z0 < z_i - band
            out["upper_mean_dx_over_ring"] = float(dx[upper].mean() / travel) if upper.any() and travel > 0 else 0.0
            out["lower_mean_dx_over_ring"] = float(dx[lower].mean() / travel) if lower.any() and travel > 0 else 0.0
        return out


PROTOCOLS = {"prepare": Prepare, "shear": Shear}


def make_simulation(scn, radius, x, layer, walls, t, cyl_radius, top, bond_law=None):
    """A Simulation for a sample in a cylinder of `cyl_radius` up to height `top`."""
    from .simulation import GridTooLarge, Simulation
    m = 0.01
    try:
        return Simulation(radius, x, layer=layer, walls=walls, density=scn.material.density,
                          friction=scn.material.friction, settings=scn.solver.to_settings(),
                          bond_law=bond_law or scn.bond.to_law(),
                          domain=((-cyl_radius - m, -cyl_radius - m, 0.0),
                                  (cyl_radius + m, cyl_radius + m, top)),
                          time=t)
    except GridTooLarge as exc:
        raise ValueError(f"{scn.source}: {exc}. The domain is the mould up to the pouring "
                         "column's top: lower the prepare stage's "
                         "column_height_mm or cylinder_diameter_mm, or raise its size_scale "
                         "(larger grains)") from None
