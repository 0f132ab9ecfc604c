"""The preparation's phases and the shear's set-up and results (tcd/protocols.py; PHYSICS.md
sections 7-8) on stub simulations, against hand-worked values (session 43's mutation audit: a
3 mm amplitude, a frequency read as rad/s, a confinement at 60 mm, one size table for both
courses, the gap on each side of the split plane and more passed the suite before). No
simulation runs."""
import math
import types

import numpy as np
import pytest

from tcd import packing, walls
from tcd.config import parse_scenario
from tcd.protocols import Prepare, Shear, servo_step, settled

PAPER = 'name = "t"\n\n[[stage]]\nkind = "prepare"\n\n[[stage]]\nkind = "shear"\n'


def _stub_sim(top: float, plate: float | None = None):
    """Two unit grains of 1 mm radius, the highest reaching `top`, and (optionally) a plate."""
    x = np.array([[0.0, 0.0, 0.001], [0.0, 0.0, top - 0.001]])
    r = np.array([0.001, 0.001])
    wl = [walls.plane((0, 0, 0), (0, 0, 1)), walls.cylinder((0, 0, 0), (0, 0, 1), 0.075, (0, 1))]
    if plate is not None:
        wl.append(walls.plane((0, 0, plate), (0, 0, -1)))
    return types.SimpleNamespace(positions=lambda: x, radii=lambda: r, walls=wl)


def test_vibration_phase_is_6_mm_at_30_hz_for_one_second_toward_each_course_height():
    scn = parse_scenario(PAPER)
    prep = Prepare(scn.stages[0], scn, 1)
    h = scn.solver.time_step
    for L in (0, 1):
        phase, _ = prep.plan(3 * L + 1, _stub_sim(0.07 + 0.06 * L), 0.0)
        sv = phase.info["servo"]
        assert phase.name == "vibrate" and phase.info["layer"] == L
        assert sv["amplitude"] == pytest.approx(6e-3) and sv["frequency"] == pytest.approx(30.0)
        assert phase.steps == round(1.0 / h) and not phase.settle
        assert sv["target"] == pytest.approx(0.060 * (L + 1))           # 60 mm, then 120 mm
        assert sv["v_mean"] == pytest.approx((sv["target"] - sv["z0"]) / 1.0)
        # the plate can follow the sine: peak speed 2 pi f A plus the descent
        assert sv["v_max"] == pytest.approx(2 * math.pi * 30.0 * 6e-3 + abs(sv["v_mean"]))
    phase, _ = prep.plan(6, _stub_sim(0.125, plate=0.125), 0.0)           # confine
    assert phase.name == "confine" and phase.info["target"] == pytest.approx(0.120)
    assert phase.info["servo"]["amplitude"] == 0.0


def test_servo_plate_oscillates_at_the_frequency_in_hertz():
    """Below the force limit and the speed cap, the plate is at
    max(target, z0 + v_mean s) + A sin(2 pi f s), s the time since the phase began."""
    h, A, f, z0 = 1e-4, 6e-3, 30.0, 0.1
    plate = walls.plane((0, 0, z0), (0, 0, -1))
    sim = types.SimpleNamespace(time=0.0, settings=types.SimpleNamespace(time_step=h),
                                step_index=0, walls=[None, None, plate],
                                wall_force=lambda k: np.zeros(3))
    sim.replace_wall = lambda k, w: sim.walls.__setitem__(k, w)
    sv = {"wall": 2, "z": z0, "z0": z0, "target": 0.0, "t0": 0.0, "amplitude": A,
          "frequency": f, "force_limit": 1.0, "v_mean": -0.01, "v_max": 10.0}
    phase = types.SimpleNamespace(info={"servo": sv})
    for k in range(1, 400):
        servo_step(sim, phase)
        sim.time, sim.step_index = k * h, k
        assert sv["z"] == pytest.approx(z0 - 0.01 * k * h + A * math.sin(2 * math.pi * f * k * h),
                                        abs=1e-12)


def test_settled_compares_the_mass_weighted_rms_speed():
    """sqrt(sum m v^2 / sum m), m ~ r^3: grains of radius 1 and 2 at 9 and 1 mm/s give
    sqrt((81 + 8) / 9) mm/s = 3.145 mm/s."""
    v = np.array([[0.009, 0.0, 0.0], [0.0, 0.0, 0.001]])
    sim = types.SimpleNamespace(velocities=lambda: v, radii=lambda: np.array([1.0, 2.0]))
    rms = math.sqrt((81 + 8) / 9) * 1e-3
    assert settled(sim, rms * 1.001) and not settled(sim, rms * 0.999)


def test_each_course_gets_its_own_size_table():
    scn = parse_scenario(PAPER)
    c = scn.stages[0]
    prep = Prepare(c, scn, 1)
    for L, course in enumerate(c.courses):
        r = prep.layer_radii(L)
        d = np.round(2e3 * r / c.size_scale, 6)
        n = packing.class_counts(course, c.layer_particle_count(course))
        assert [int(np.count_nonzero(d == dk)) for dk in (2.0, 5.6, 8.0, 11.2, 16.0)] == n.tolist()
    assert 2 * prep.layer_radii(1).max() < 0.016           # no 16 mm grain in the surface course


def test_shear_record_moves_at_50_mm_per_min_and_divides_by_pi_R2():
    """The shear's measure on the paper's default stage (tests/test_runner.py checks it on a
    run's series): a stub simulation 60 s into the shear whose grains push the ring (wall 2) by
    1000 N along +x (the wall force -1000 N): the ring has moved 50 mm, tau = 1000 / (pi
    0.075^2) = 56.588 kPa."""
    scn = parse_scenario(PAPER)
    shear = Shear(scn.stages[1], scn, 1)
    forces = {2: np.array([-1000.0, 0.0, 0.0]), 3: np.zeros(3)}
    # two grains of 1 kg orbiting the axis at 2 rad/s, 1 and 2 cm from it
    x = np.array([[0.01, 0.0, 0.05], [0.0, -0.02, 0.05]])
    v = np.array([[0.0, 0.02, 0.0], [0.04, 0.0, 0.0]])
    sim = types.SimpleNamespace(time=70.0, wall_force=lambda k: forces[k],
                                bonds_state_counts=lambda: (5, 0, 0), positions=lambda: x,
                                velocities=lambda: v, angular_velocities=lambda: 0 * v,
                                inverse_masses=lambda: (np.ones(2), np.zeros(2)))
    phase = types.SimpleNamespace(info={"radius": 0.075, "t0": 10.0})
    rec = shear.record(sim, phase)
    assert rec["displacement"] == pytest.approx(0.05, rel=1e-12)
    assert rec["shear_force"] == pytest.approx(1000.0, rel=1e-12)
    assert rec["shear_stress"] == pytest.approx(56588.0, rel=1e-4)
    assert rec["spin"] == pytest.approx(2.0, rel=1e-12)
    # the velocities the runner read for the kinetic energy are not read again
    reads = types.SimpleNamespace(**{k: getattr(sim, k) for k in vars(sim)
                                     if k not in ("velocities", "angular_velocities")})
    assert shear.record(reads, phase, (v, 0 * v)) == rec


def test_shear_rings_split_at_mid_height_with_the_gap_centred_and_the_upper_ring_moving():
    """A sample whose grains reach 118 mm under a plate at 120 mm: H = 118 mm, the split plane
    at 59 mm, the 1 mm gap from 58.5 to 59.5 mm; the upper ring and the top plate move at
    50 mm/min along x, the lower ring stays."""
    scn = parse_scenario(PAPER)
    c = scn.stages[1]
    shear = Shear(c, scn, 1)
    x = np.array([[0.0, 0.0, 0.01], [0.0, 0.0, 0.117]])
    r = np.array([0.001, 0.001])
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=0.075),
          walls.cylinder((0, 0, 0), (0, 0, 1), 0.075, (0, 0.2)),
          walls.plane((0, 0, 0.12), (0, 0, -1), radius=0.075)]
    sim = types.SimpleNamespace(positions=lambda: x, radii=lambda: r, walls=wl, bond_law=None,
                                set_walls=lambda w: None, create_bonds=lambda tol: 0,
                                close=lambda: None)
    sim.renumber = lambda order: sim
    phase, _ = shear.plan(0, sim, 0.0)
    bottom, lower, upper, top = phase.walls
    assert phase.info["z_interface"] == pytest.approx(0.059)
    assert lower.extent[1] == pytest.approx(0.0585) and upper.extent[0] == pytest.approx(0.0595)
    assert lower.extent[0] <= 0.0 and upper.extent[1] >= 0.118
    v = 50e-3 / 60
    assert lower.motion == "fixed" and bottom.motion == "fixed"
    assert upper.motion == "constant" and upper.velocity == pytest.approx((v, 0.0, 0.0))
    assert top.motion == "constant" and top.velocity == pytest.approx((v, 0.0, 0.0))
    assert top.point[2] == pytest.approx(0.118)


def test_shear_finish_residual_at_the_end_and_near_plane_band_a_quarter_ring():
    """The peak and the residual (the smoothed stress at the end) of a shear, and: ring height
    60 mm: bonds within 15 mm of the split plane are near it. Five bonds: intact between equal
    grains at 10 and 20 mm above it, intact between an 8 mm and a 1 mm grain whose gap's
    middle is 18 mm above it (their centres' midpoint, 14.5 mm, would be near), and broken at
    5 and 25 mm below it (where they broke, the middle of their gap)."""
    scn = parse_scenario(PAPER)
    shear = Shear(scn.stages[1], scn, 1)
    z_i = 0.06
    x = np.array([[0, 0, z_i + 0.009], [0, 0, z_i + 0.011], [0, 0, z_i + 0.019],
                  [0, 0, z_i + 0.021], [0, 0, 0.1], [0, 0, 0.1],
                  [0, 0, z_i + 0.010], [0, 0, z_i + 0.019]], dtype=float)
    r = np.array([0.001] * 6 + [0.008, 0.001])
    st = {"bonds/state": np.array([0, 0, 0, 1, 2]), "bonds/i": np.array([0, 2, 6, 4, 4]),
          "bonds/j": np.array([1, 3, 7, 5, 5]),
          "bonds/broken_pos": np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, z_i - 0.005],
                                        [0, 0, z_i - 0.025]], dtype=float)}
    sim = types.SimpleNamespace(state_dict=lambda: st, positions=lambda: x, radii=lambda: r, n=8,
                                time=0.0)
    phase = types.SimpleNamespace(info={"z_interface": z_i, "sample_height": 0.12,
                                        "radius": 0.075, "t0": 0.0})
    d = np.linspace(0, 2.5e-3, 51)
    # a rise to 1 MPa at 1 mm, then a drop to a 0.3 MPa plateau: the residual is its end
    tau = np.where(d <= 1e-3, 1e6 * d / 1e-3, np.where(d < 1.5e-3, 1e6, 0.3e6))
    out = shear.finish(sim, phase, {"displacement": d, "shear_stress": tau})
    assert out["residual_MPa"] == pytest.approx(0.3, rel=1e-12)
    assert out["tau_peak_MPa"] == pytest.approx(1.0, rel=1e-12)
    assert out["near_plane_band_mm"] == pytest.approx(15.0)
    assert out["bonds_near_plane_fraction"] == pytest.approx(0.4)
    assert out["broken_near_plane_fraction"] == pytest.approx(0.5)
    assert (out["bonds_broken_tension"], out["bonds_broken_shear"]) == (1, 1)


def _bondless_shear(x, radius=0.001):
    """The paper's shear stage and a stub of its simulation 3 s in (the ring moved 2.5 mm):
    grains at `x` of one `radius`, no bonds; the phase of a 75 mm mould split at 60 mm."""
    scn = parse_scenario(PAPER)
    st = {"bonds/state": np.zeros(0, int), "bonds/i": np.zeros(0, int),
          "bonds/j": np.zeros(0, int), "bonds/broken_pos": np.zeros((0, 3))}
    sim = types.SimpleNamespace(state_dict=lambda: st, positions=lambda: x, n=len(x),
                                radii=lambda: np.full(len(x), radius), time=3.0)
    phase = types.SimpleNamespace(info={"z_interface": 0.06, "sample_height": 0.12,
                                        "radius": 0.075, "t0": 0.0})
    return Shear(scn.stages[1], scn, 1), sim, phase


def test_a_shear_whose_kinetic_energy_nears_the_walls_work_is_flagged():
    """A quasi-static shear keeps its grains' kinetic energy far below the walls' work (the
    study's: at most 2.9e-4 of it); a grain flung by the instability of docs/physics.md's known
    limitations shows as a ratio near 1. Above 0.01 the stage's numbers carry a warning
    (session 44), which `tcd run` prints."""
    shear, sim, phase = _bondless_shear(np.zeros((2, 3)))
    d = np.linspace(0, 2.5e-3, 51)
    force = np.full(51, 100.0)                   # 100 N over 2.5 mm: 0.25 J of work
    for ke, flagged in ((2.4e-3, False), (2.6e-3, True), (0.2, True)):
        series = {"displacement": d, "shear_stress": force / (math.pi * 0.075**2),
                  "shear_force": force, "top_plate_shear_force": np.zeros(51),
                  "kinetic_energy": np.full(51, ke)}
        out = shear.finish(sim, phase, series)
        assert out["kinetic_over_work_max"] == pytest.approx(ke / 0.25)
        assert ("warnings" in out) == flagged, ke
        if flagged:
            assert f"reached {ke / 0.25:.3g} of the walls' work" in out["warnings"][0]


def test_grains_squeezed_out_between_the_rings_are_counted_and_named():
    """A gap wider than the smallest grains let them out of the mould, unsaid (the user audit
    of session 48). Rings of 75 mm, the upper one 2.5 mm along x: a grain above the plane at
    x = 77 mm is inside the upper ring (76.0 < 77.5), one at y = 76 mm is out of it, one below
    the plane at x = 76 mm is out of the lower ring."""
    x = np.array([[0.077, 0.0, 0.07], [0.0, 0.076, 0.07], [0.076, 0.0, 0.05], [0.0, 0.0, 0.05]])
    shear, sim, phase = _bondless_shear(x, radius=0.0004)
    d = np.linspace(0, 2.5e-3, 51)
    out = shear.finish(sim, phase, {"displacement": d, "shear_stress": np.full(51, 1e5)})
    assert out["outside"] == 2
    assert out["warnings"] == ["2 grain(s) ended outside the rings (their centres beyond the "
                               "75 mm radius), squeezed out between them: the gap is 1 mm, the "
                               "smallest grains 0.8 mm across (keep gap_mm below it)"]


def test_a_sample_turning_about_the_mould_s_axis_is_flagged():
    """Frictionless rings let a sheared sample turn as a whole (session 48: `tiny.toml`'s rim
    23 times as far as the ring moved). The summary gives the spin's largest value and the
    turn by the peak, both over the ring's, and warns when the rim turned farther than the
    ring moved; a brief spike (bonds breaking) turns the rim little and is not flagged."""
    shear, sim, phase = _bondless_shear(np.zeros((2, 3)))
    t = np.linspace(0.0, 3.0, 301)
    d = t * 50e-3 / 60.0                         # 2.5 mm at 50 mm/min
    tau = np.where(d < 2e-3, d / 2e-3, 1.0) * 1e6      # the peak at the end (d = 2.5 mm)
    ring = 50e-3 / 60.0 / 0.075                  # the spin whose rim moves at the ring's speed
    for spin, turn, flagged in ((np.full(301, 1.2 * ring), 1.2, True),
                                (np.full(301, 0.8 * ring), 0.8, False),
                                (np.where(np.arange(301) == 150, 50 * ring, 0.0), 50 * 0.01 / 3.0, False)):
        out = shear.finish(sim, phase, {"displacement": d, "shear_stress": tau, "time": t,
                                        "spin": spin})
        assert out["turn_rim_over_ring"] == pytest.approx(turn, rel=1e-9)
        assert out["spin_rim_over_ring_max"] == pytest.approx(np.max(spin) / ring, rel=1e-12)
        assert ("warnings" in out) == flagged, turn
        if flagged:
            assert f"its rim moved {turn:.3g} times as far as the ring" in out["warnings"][0]


def test_prepared_layers_packing_fractions_average_to_the_sample_s():
    """Prepare.finish on a stub: the per-layer packing fractions are each layer's slab (bottom
    plate, equal-volume interface, top plate), so weighted by the slab heights they average to
    the sample's, and each is its own grains' volume over its slab (no interpenetration here)."""
    scn = parse_scenario(PAPER)
    prep = Prepare(scn.stages[0], scn, 1)
    xy = np.array([[0.03, 0.0], [-0.03, 0.0], [0.0, 0.03], [0.0, -0.03]])
    x = np.vstack([np.column_stack([xy, np.full(4, 0.01)]), np.column_stack([xy, np.full(4, 0.03)])])
    r = np.array([0.01] * 4 + [0.005] * 4)
    layer = np.array([0] * 4 + [1] * 4, np.int32)
    H = 0.04
    sim = types.SimpleNamespace(
        n=8, time=0.0, positions=lambda: x, radii=lambda: r,
        state_dict=lambda: {"particles/layer": layer},
        walls=[None, None, walls.plane((0, 0, H), (0, 0, -1))],
        contact_arrays=lambda: {"i": np.array([0]), "j": np.array([8]),
                                "impulse": np.zeros((1, 3)), "gap": np.array([0.0])})
    out = prep.finish(sim)
    zb = out["layer_interfaces_mm"][0] * 1e-3
    assert 0.02 - 1e-9 <= zb <= 0.025           # anywhere in the empty gap between them
    area = math.pi * 0.075**2
    pf = out["packing_fraction_per_layer"]
    assert pf[0] == pytest.approx(4 * 4 / 3 * math.pi * 0.01**3 / (area * zb), rel=1e-9)
    assert pf[1] == pytest.approx(4 * 4 / 3 * math.pi * 0.005**3 / (area * (H - zb)), rel=1e-9)
    h = np.array(out["layer_heights_mm"]) * 1e-3
    assert float(np.dot(pf, h)) / H == pytest.approx(out["packing_fraction"], rel=1e-12)

