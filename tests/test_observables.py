"""Reductions used by the prepared-sample summary, against closed forms."""
import math

import numpy as np
import pytest

from tcd import observables as obs


def lattice(nx, nz, r, z0):
    g = np.arange(nx) * 2 * r
    xs = [(x, y, z0 + r + 2 * r * k) for x in g for y in g for k in range(nz)]
    return np.array(xs, float)


def test_layer_interface_of_two_stacked_lattices_is_their_contact_plane():
    r = 0.001
    lower = lattice(4, 3, r, 0.0)                 # tops at 6 r
    upper = lattice(4, 2, r, 6 * r)
    x = np.concatenate([lower, upper])
    rad = np.full(len(x), r)
    layer = np.array([0] * len(lower) + [1] * len(upper))
    # (both volumes vanish quadratically at the plane: the root is found to ~1e-8 r)
    assert abs(obs.layer_interface(x, rad, layer, 0, 1) - 6 * r) < 1e-7 * r
    # interpenetrating layers: the upper one sunk by half a radius -> the plane splits it evenly
    upper2 = upper - [0, 0, 0.5 * r]
    x2 = np.concatenate([lower, upper2])
    zb = obs.layer_interface(x2, rad, layer, 0, 1)
    above = obs.slab_volume(lower[:, 2], rad[: len(lower)], zb, 1.0).sum()
    below = obs.slab_volume(upper2[:, 2], rad[len(lower):], -1.0, zb).sum()
    assert abs(above - below) < 1e-9 * above
    assert 5.5 * r < zb < 6 * r


def test_slab_packing_fractions_add_up():
    rng = np.random.default_rng(3)
    r = rng.uniform(0.001, 0.004, 300)
    x = np.column_stack([rng.uniform(-0.02, 0.02, 300), rng.uniform(-0.02, 0.02, 300),
                         rng.uniform(0.005, 0.045, 300)])
    total = obs.packing_fraction(x, r, 0.03, 0.0, 0.05)
    a = obs.packing_fraction(x, r, 0.03, 0.0, 0.02)
    b = obs.packing_fraction(x, r, 0.03, 0.02, 0.05)
    assert abs((0.02 * a + 0.03 * b) / 0.05 - total) < 1e-12
    assert abs(total * math.pi * 0.03**2 * 0.05 - (4 / 3 * math.pi * r**3).sum()) < 1e-15


def test_study_statistics_average_finite_values_and_compare_with_the_experiments():
    samples = [{"seed": 1, "tau_peak_MPa": 0.9, "d_peak_mm": 2.0, "residual_MPa": 0.5},
               {"seed": 2, "tau_peak_MPa": 1.1, "d_peak_mm": 2.4, "residual_MPa": None},
               {"seed": 3},                                   # no peak: left out
               {"seed": 4, "tau_peak_MPa": float("nan"), "d_peak_mm": 2.6, "residual_MPa": 0.7}]
    mean, std, rel = obs.study_statistics(samples)
    assert mean["tau_peak_MPa"] == pytest.approx(1.0) and std["tau_peak_MPa"] == pytest.approx(0.1)
    assert mean["d_peak_mm"] == pytest.approx(7.0 / 3.0)
    assert std["d_peak_mm"] == pytest.approx(np.std([2.0, 2.4, 2.6]))
    assert mean["residual_MPa"] == pytest.approx(0.6)
    assert rel["tau_peak"] == pytest.approx(1.0 / 0.898 - 1.0)
    assert rel["d_peak"] == pytest.approx((7.0 / 3.0) / 2.37 - 1.0)
    _, _, rel = obs.study_statistics(samples, {"tau_peak_MPa": 1.0})
    assert rel["tau_peak"] == pytest.approx(0.0)
    assert obs.study_statistics([{"seed": 1}]) == ({}, {}, {})


def test_layer_highest_and_99th_percentile_tops():
    """Each layer's highest grain top (where a plate would rest) and the 99th percentile of its
    grain tops: 101 grains of one layer stacked 1 mm apart, and one grain of another."""
    z = np.concatenate([np.arange(101) * 1e-3, [0.5]])
    x = np.column_stack([np.zeros(102), np.zeros(102), z])
    r = np.full(102, 2e-4)
    layer = np.array([1] * 101 + [0])
    assert obs.layer_highest(x, r, layer) == pytest.approx([0.5002, 0.1002], rel=1e-12)
    # 99th percentile of 0.0002 .. 0.1002 in steps of 1 mm, linear interpolation: 0.0992
    assert obs.layer_tops(x, r, layer) == pytest.approx([0.5002, 0.0992], rel=1e-12)


def test_outside_counts_spheres_through_the_mould_or_a_plate_beyond_the_slack():
    """The slack is 1 % of the smallest diameter: 0.02 mm for 1 mm radii in a 10 mm mould."""
    r = np.full(5, 1e-3)
    x = np.array([[0.0, 0, 0.005],               # well inside
                  [0.009 + 1.5e-5, 0, 0.005],    # through the mould by 0.015 mm: inside the slack
                  [0.009 + 2.5e-5, 0, 0.005],    # by 0.025 mm: outside
                  [0.0, 0, 0.001 - 2.5e-5],      # through the bottom plate
                  [0.0, 0, 0.009 + 2.5e-5]])     # through the top plate at 10 mm
    assert obs.outside(x, r, 0.01, 0.0, 0.01) == 3
    # the mould's axis moved by 1 mm along x: the grain at the centre line stays in, the
    # two near its wall at +x are further in, and none is pushed out on the -x side
    assert obs.outside(x, r, 0.01, 0.0, 0.01, axis=(0.001, 0.0)) == 2


def test_coordination_counts_listed_pairs_or_the_ones_that_carried_a_force():
    """Five grains in a row along x, contacts 0-1 pressed (impulse on j along x_j - x_i),
    1-2 listed within the alert distance but carrying nothing, 2-3 with an impulse that pulls
    them together (a reversed sign: not a compression), 3-4 pressed with a tangential part,
    and grain 0 on a wall: 4 listed pairs (8 / 5 per grain), 2 that carried a force (4 / 5).
    Session 42: the summaries' `coordination_number` counts the listed pairs (5.01 on the
    shipped seed-1 sample, whose grains pressed on 4.01 per grain)."""
    x = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]]) * 0.01
    i = np.array([0, 1, 2, 3, 0])
    j = np.array([1, 2, 3, 4, 5])                       # the last: wall 0 (j >= n)
    impulse = np.array([[2e-4, 0, 0], [0, 0, 0], [-1e-4, 0, 0], [3e-4, 1e-4, 0], [0, 0, 5e-4]])
    loaded = obs.carries_force(i, j, impulse, x)
    assert loaded.tolist() == [True, False, False, True, False]
    assert obs.coordination_number(i, j, 5) == pytest.approx(8 / 5)
    assert obs.coordination_number(i, j, 5, loaded) == pytest.approx(4 / 5)


def test_slab_volume_of_a_cap_is_pi_h2_3r_minus_h_over_3():
    """A sphere cut at a height h above its bottom: the cap below holds pi h^2 (3 r - h) / 3
    (h = r / 2: 5 pi r^3 / 24). The slab totals and the symmetric cases of layer_interface
    cannot tell a cap from any other volume that is 0 at h = 0 and 4/3 pi r^3 at h = 2 r."""
    r = 0.002
    z = np.array([0.01])
    cap = obs.slab_volume(z, np.array([r]), -1.0, z[0] - r + 0.5 * r)
    assert cap[0] == pytest.approx(5.0 * math.pi * r**3 / 24.0, rel=1e-14)
    top = obs.slab_volume(z, np.array([r]), z[0] + 0.5 * r, 1.0)     # the cap r / 2 high above
    assert top[0] == pytest.approx(math.pi * (0.5 * r) ** 2 * (3 * r - 0.5 * r) / 3.0, rel=1e-14)


def test_kinetic_energy_counts_the_spin_with_two_fifths_m_r2_and_the_masses_of_a_loaded_state():
    """A simulation's kinetic energy from its own masses: 1/2 m v^2 + 1/2 (2/5 m r^2) w^2 of
    its density; after load_state_dict, the masses of the loaded state (the API audit of
    session 44: it used the new simulation's density, 2.6 times too much for a state of
    density 1000 loaded into one of 2600); a kinematic (fixed) grain carries none."""
    from tcd import backend
    from tcd.simulation import Simulation, SolverSettings
    rho = 2600.0
    r = np.array([0.004, 0.002, 0.003])
    m = rho * 4.0 / 3.0 * math.pi * r**3
    x = [[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.04, 0.0, 0.0]]
    v = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.5, 0.0]])
    w = np.array([[0.0, 0.0, 0.0], [0.0, 30.0, 0.0], [7.0, 0.0, 0.0]])
    settings = SolverSettings(gravity=(0.0, 0.0, 0.0))
    rel = 1e-13 if backend.precision() == "f64" else 1e-6
    sim = Simulation(r, x, density=rho, velocity=v, settings=settings)
    sim.set_angular_velocities(w)
    exact = float(np.sum(0.5 * m * np.sum(v**2, axis=1) + 0.2 * m * r**2 * np.sum(w**2, axis=1)))
    assert sim.kinetic_energy() == pytest.approx(exact, rel=rel)
    light = Simulation(r, x, density=1000.0, velocity=v, settings=settings)
    light.set_angular_velocities(w)
    sim.load_state_dict(light.state_dict())
    assert sim.kinetic_energy() == pytest.approx(exact * 1000.0 / rho, rel=rel)
    held = Simulation(r, x, density=rho, velocity=v, fixed=[False, False, True], settings=settings)
    held.set_angular_velocities(w)
    assert held.kinetic_energy() == pytest.approx(0.5 * m[0] * 0.01 + 0.2 * m[1] * r[1]**2 * 900.0,
                                                  rel=rel)
    for o in (sim, light, held):
        o.close()


def test_smooth_window_includes_both_edges():
    """|x_j - x_i| <= window / 2 on both sides: on integer abscissae with a window of 2 the
    average of i-1, i, i+1 (exact in floating point), the ends averaging what they have."""
    x = np.arange(6.0)
    np.testing.assert_allclose(obs.smooth(x.copy(), x, 2.0), [0.5, 1, 2, 3, 4, 4.5], rtol=0, atol=1e-15)



def test_study_statistics_do_not_depend_on_the_order_of_the_samples():
    """A study run as `--seeds 5,4,3,2,1` averaged its samples in that order, and `tcd figures`
    in the seeds' order: their means and stds could differ in the last bit (session 48)."""
    rng = np.random.default_rng(7)
    for _ in range(200):        # peaks whose sum rounds differently in the two orders
        values = rng.uniform(0.8, 1.0, 5)
        if np.mean(values) != np.mean(values[::-1]) or np.std(values) != np.std(values[::-1]):
            break
    else:
        pytest.fail("no order-dependent sum found")
    samples = [{"seed": k + 1, "tau_peak_MPa": float(v), "d_peak_mm": 2.0 + float(v)}
               for k, v in enumerate(values)]
    forward = obs.study_statistics(samples)
    assert obs.study_statistics(samples[::-1]) == forward
    assert obs.study_statistics(samples[2:] + samples[:2]) == forward
    assert forward[0]["tau_peak_MPa"] == float(np.mean(values))     # the seeds' order


def test_spin_about_axis_is_the_rigid_rotation_of_the_bodies():
    """A rigid rotation at omega about a vertical axis through c (orbits and the bodies' own
    spins) reads omega; a translation reads 0; a kinematic body does not count."""
    rng = np.random.default_rng(3)
    n = 50
    x = rng.uniform(-0.02, 0.02, (n, 3))
    r = rng.uniform(1e-3, 3e-3, n)
    m = 2600 * 4 / 3 * np.pi * r**3
    inv_m, inv_i = 1 / m, 1 / (0.4 * m * r**2)
    c, omega = (0.004, -0.002), 3.7
    v = np.zeros((n, 3))
    v[:, 0], v[:, 1] = -omega * (x[:, 1] - c[1]), omega * (x[:, 0] - c[0])
    w = np.tile([0.0, 0.0, omega], (n, 1))
    assert obs.spin_about_axis(x, v, w, inv_m, inv_i, c) == pytest.approx(omega, rel=1e-12)
    # orbits alone: the bodies' own inertia about their centres counts in I_z, not in L_z
    got = obs.spin_about_axis(x, v, 0 * w, inv_m, inv_i, c)
    rho2 = (x[:, 0] - c[0])**2 + (x[:, 1] - c[1])**2
    assert got == pytest.approx(omega * np.sum(m * rho2) / (np.sum(m * rho2) + np.sum(1 / inv_i)))
    assert obs.spin_about_axis(x, v + [0.3, -0.1, 0.2], w, inv_m, inv_i, c) != pytest.approx(omega)
    moving = np.tile([0.3, -0.1, 0.2], (n, 1))        # a translation, about the mass centre
    com = np.sum(m[:, None] * x, axis=0) / np.sum(m)
    assert abs(obs.spin_about_axis(x, moving, 0 * w, inv_m, inv_i, com[:2])) < 1e-12
    inv_m[0] = inv_i[0] = 0.0          # kinematic: driven, infinite mass
    v2 = v.copy()
    v2[0] = [50.0, 50.0, 0.0]
    assert obs.spin_about_axis(x, v2, w, inv_m, inv_i, c) == pytest.approx(omega, rel=1e-12)


def test_paper_test_differences_name_each_departure_from_the_leutner_test():
    diff = obs.paper_test_differences
    assert diff(50.0, 2.5, [150.0, 150.0], [118.2, 118.9]) == []
    assert diff(50.2, 3.0, [150.0], [np.nan]) == []        # within 1 %; beyond 2.5 mm; unknown
    assert diff(50.0, 2.5, [], []) == []                    # samples that do not say
    assert diff(600.0, 0.4, [30.0], [10.0]) == [
        "a shear at 600 mm/min (the paper's: 50)",
        "a shear to 0.4 mm (the paper's: to 2.5 mm; the experiments' peak is at 2.37 mm)",
        "a mould of 30 mm (the paper's: 150 mm)",
        "a sample height of 10 mm (the paper's: 120 mm)"]
    assert diff(50.0, 2.3, [150.0, 140.0, 130.0], [None, 113.0, 126.5]) == [
        "a shear to 2.3 mm (the paper's: to 2.5 mm; the experiments' peak is at 2.37 mm)",
        "a mould of 130-140 mm (the paper's: 150 mm)",
        "a sample height of 113-126.5 mm (the paper's: 120 mm)"]
    assert diff(float("nan"), 2.5)[0].startswith("a shear at nan mm/min")
