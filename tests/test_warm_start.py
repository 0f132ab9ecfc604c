"""The extrapolated warm start (SolverSettings.warm_start_extrapolation, issue 8).

Each bond, and each contact that carried an impulse at the last two steps, starts the step from
R_n + c (R_n - R_n-1) instead of R_n. Only the starting point of the Gauss-Seidel moves: a
steady load must still be carried exactly, a loading that grows steadily must give the same
motion to the solver's tolerance in fewer sweeps, and a saved state must carry R_n-1 so that a
resumed run continues bit for bit.
"""
import numpy as np
import pytest

from tcd import backend, io, walls
from tcd.simulation import BondLaw, Simulation, SolverSettings
from tcd.state import get

from test_bonds import truss

G = 9.81
H = 2e-4


def test_resting_sphere_still_carries_m_g_h(tol):
    r = 0.004
    sim = Simulation([r], [[0, 0, r]], walls=[walls.plane((0, 0, 0), (0, 0, 1))],
                     settings=SolverSettings(tolerance=1e-12, max_sweeps=100,
                                             warm_start_extrapolation=1.0),
                     domain=((-0.01,) * 3, (0.01,) * 3))
    m = 1.0 / float(get(sim.particles.inv_mass, 1)[0])
    for _ in range(20):
        sim.step()
        c = sim.contact_arrays()
        np.testing.assert_allclose(c["impulse"][0], [0, 0, -m * G * H], rtol=tol, atol=1e-20)
    np.testing.assert_allclose(sim.velocities()[0], 0.0, atol=1e-12 if tol < 1e-6 else 1e-7)


def _ramped_cantilever(c: float, steps: int = 300, tolerance: float = 1e-7):
    """A bonded truss clamped at one end, its tip pulled down by a force growing linearly
    in time (so every bond impulse grows about linearly): tip path and sweeps per step."""
    r = 0.004
    x = truss(r, 6)
    fixed = np.zeros(len(x), bool)
    fixed[0] = fixed[7] = True
    sim = Simulation([r] * len(x), x, fixed=fixed,
                     settings=SolverSettings(tolerance=tolerance, max_sweeps=5000,
                                             gravity=(0, 0, 0), warm_start_extrapolation=c),
                     bond_law=BondLaw(mode="burgers", yield_stress=1e12),
                     domain=((-0.01, -0.01, -0.1), (0.06, 0.01, 0.02)))
    assert sim.create_bonds(gap_tolerance=1e-7) == 6 + 5 + 12
    tip = 6
    f = np.zeros((len(x), 3))
    path, sweeps = [], []
    for k in range(steps):
        f[tip, 2] = -2.0 * (k + 1) / steps          # up to 2 N
        sim.set_external_force(f)
        rec = sim.step()
        path.append(sim.positions()[tip, 2] - x[tip, 2])
        sweeps.append(rec.sweeps)
    return np.array(path), np.array(sweeps)


def test_ramped_load_same_motion_in_fewer_sweeps(precision):
    # 1e-7 is the relative impulse change of a sweep; in f32 that is near the rounding of the
    # impulse sums themselves (2^-24 = 6e-8), where the sweeps count noise, not convergence
    # (c = 0: 87792 sweeps, c = 1: 55650, 186 per step where f64 takes 43). At 1e-5 f32
    # gives 24840 against 5001 (session 40).
    tolerance = 1e-7 if precision == "f64" else 1e-5
    path0, sweeps0 = _ramped_cantilever(0.0, tolerance=tolerance)
    path1, sweeps1 = _ramped_cantilever(1.0, tolerance=tolerance)
    assert path0[-1] < -1e-6                     # the tip really moves
    # the same motion to the solver's tolerance (f32 rounding sets the floor there)
    np.testing.assert_allclose(path1, path0, rtol=0, atol=abs(path0[-1]) * (1e-4 if precision == "f64" else 2e-3))
    # c = 1 extrapolates a linear growth exactly: 43 sweeps per step against 300 (f64)
    assert sweeps1.sum() < 0.5 * sweeps0.sum(), (sweeps1.sum(), sweeps0.sum())


def _bonded_pile(c: float):
    """A 3 x 3 x 3 lattice of touching spheres on a floor, bonded, pushed sideways by a
    growing force on its top layer: bonds and lasting floor contacts."""
    r = 0.004
    g = np.arange(3) * 2 * r
    x = np.array([[a, b, r + z] for a in g for b in g for z in g])
    sim = Simulation(np.full(len(x), r), x, walls=[walls.plane((0, 0, 0), (0, 0, 1))],
                     settings=SolverSettings(tolerance=1e-6, max_sweeps=500,
                                             warm_start_extrapolation=c),
                     bond_law=BondLaw(mode="burgers"),
                     domain=((-0.01,) * 3, (0.03, 0.03, 0.03)))
    sim.step(3)
    assert sim.create_bonds(1e-6) > 40
    return sim


def _push(sim, k):
    f = np.zeros((sim.n, 3))
    top = sim.positions()[:, 2] > 0.015
    f[top, 0] = 1e-3 * k
    sim.set_external_force(f)


@pytest.mark.f64_only   # compares two runs of the same code: once, in f64, is enough
def test_state_carries_the_previous_impulses_and_resumes_bit_for_bit(tmp_path):
    a = _bonded_pile(0.5)
    for k in range(40):
        _push(a, k)
        a.step()
    d = a.state_dict()
    # R_n-1 really differs from R_n (else the test could not see a lost history)
    assert not np.array_equal(d["bonds/impulse_prev"], d["bonds/impulse"])
    floor = d["contacts/j"] >= a.n
    assert floor.sum() >= 9
    assert not np.array_equal(d["contacts/impulse_old"][floor], d["contacts/impulse"][floor])
    path = tmp_path / "state.h5"
    io.save_checkpoint(path, d, {"time": a.time})
    arrays, meta = io.load_checkpoint(path)
    b = Simulation(arrays["particles/radius"], arrays["particles/x"],
                   walls=[walls.plane((0, 0, 0), (0, 0, 1))], bond_law=a.bond_law,
                   settings=a.settings, domain=a.domain, time=meta["time"])
    b.load_state_dict(arrays)
    for k in range(40, 70):
        for o in (a, b):
            _push(o, k)
            o.step()
    da, db = a.state_dict(), b.state_dict()
    for key in ("particles/x", "particles/v", "bonds/impulse", "bonds/impulse_prev",
                "contacts/impulse", "contacts/impulse_old"):
        assert np.array_equal(da[key], db[key]), key


@pytest.mark.f64_only
def test_a_state_without_the_previous_impulses_starts_without_extrapolating():
    """A state written before this setting existed lacks R_n-1: its first step then starts
    from R_n, the step of the plain warm start, bit for bit."""
    a = _bonded_pile(0.0)
    for k in range(20):
        _push(a, k)
        a.step()
    old = {k: v for k, v in a.state_dict().items()
           if k not in ("bonds/impulse_prev", "contacts/impulse_old")}
    out = []
    for c in (0.0, 0.5):
        s = Simulation(old["particles/radius"], old["particles/x"],
                       walls=[walls.plane((0, 0, 0), (0, 0, 1))], bond_law=a.bond_law,
                       settings=SolverSettings(tolerance=1e-6, max_sweeps=500,
                                               warm_start_extrapolation=c),
                       domain=a.domain, time=a.time)
        s.load_state_dict(old)
        _push(s, 20)
        s.step()
        out.append(s.state_dict())
    for key in ("particles/v", "bonds/impulse", "contacts/impulse"):
        assert np.array_equal(out[0][key], out[1][key]), key


def test_a_resting_contact_warm_started_from_its_last_impulse_converges_at_once():
    """PHYSICS.md section 6: each contact starts from its impulse of the last step. A sphere at
    rest on a plane carries m g H every step: warm-started, the first sweep changes nothing
    (residual 0, one sweep with check_every = 1); cold, it changes all of it (residual 1, a
    second sweep). (A dropped warm start of the compressive contacts passed every other test.)"""
    r = 0.004
    sim = Simulation([r], [[0, 0, r]], walls=[walls.plane((0, 0, 0), (0, 0, 1))],
                     settings=SolverSettings(tolerance=1e-9 if backend.precision() == "f64"
                                             else 1e-5, max_sweeps=100, check_every=1),
                     domain=((-0.01,) * 3, (0.01,) * 3))
    sim.step()
    assert sim.last.sweeps == 2                       # cold: 0 -> m g H, then nothing
    for _ in range(3):
        sim.step()
        assert sim.last.sweeps == 1
        assert sim.last.residual < sim.settings.tolerance
    sim.close()


@pytest.mark.parametrize("schedule", ["serial", "coloured"])
def test_each_contact_of_a_grain_is_warm_started_from_its_own_last_impulse(schedule):
    """Two spheres stacked on a plane: the lower one has two contacts, the sphere above (m g H)
    and the floor (2 m g H). Each is warm-started from the impulse of the same pair (i, j) the
    step before, so a settled stack converges in one sweep (session 69's mutation study: a
    match on i alone, which seeds the pair with the floor's 2 m g H, passed every test, their
    grains having one contact each)."""
    r, h = 0.004, 2e-4
    sim = Simulation([r, r], [[0, 0, r], [0, 0, 3 * r]], walls=[walls.plane((0, 0, 0), (0, 0, 1))],
                     settings=SolverSettings(tolerance=1e-9 if backend.precision() == "f64"
                                             else 1e-5, max_sweeps=100, check_every=1,
                                             schedule=schedule, time_step=h),
                     domain=((-0.01,) * 3, (0.01,) * 3))
    try:
        sim.step(3)
        for _ in range(3):
            sim.step()
            assert sim.last.sweeps == 1, sim.last.sweeps
        m = 1.0 / sim.inverse_masses()[0][0]
        c = sim.contact_arrays()
        wall = c["j"] >= 2
        # (each impulse along the vertical: its sign is the list's convention, i to j)
        pair_r, wall_r = np.abs(c["impulse"][~wall][0]), np.abs(c["impulse"][wall][0])
        np.testing.assert_allclose(pair_r, [0, 0, m * 9.81 * h], rtol=1e-4, atol=1e-12)
        np.testing.assert_allclose(wall_r, [0, 0, 2 * m * 9.81 * h], rtol=1e-4, atol=1e-12)
    finally:
        sim.close()


# --- session 43's mutation audit of the schedules, batching and the grid ------------------
def test_the_warm_start_is_extrapolated_once():
    """With warm_start_extrapolation c the step starts each bond, and each contact that carried
    an impulse the step before, from R_n + c (R_n - R_n-1) (a contact's with a negative normal
    part from zero). Kills: the extrapolation applied with 2 c (contacts, bonds)."""
    from test_batch import pour as bpour
    c = 0.5
    sim = bpour(1, settings=SolverSettings(max_sweeps=300, schedule="serial",
                                           warm_start_extrapolation=c))
    sim.step(200)
    assert sim.create_bonds(2e-4) > 20
    sim.step(5)
    d0 = sim.state_dict()
    sim._begin_step()                    # up to the warm start (contacts built, bonds prepared)
    d1 = sim.state_dict()
    # bonds: the same bonds, in the same order
    rb, rb_old = d0["bonds/impulse"], d0["bonds/impulse_prev"]
    intact = d0["bonds/state"] == 0
    expect = rb + c * (rb - rb_old)
    assert np.abs(rb - rb_old)[intact].max() > 1e-3 * np.abs(rb[intact]).max()
    np.testing.assert_allclose(d1["bonds/impulse"][intact], expect[intact], rtol=1e-12,
                               atol=1e-15 * np.abs(rb).max())
    # contacts: matched by pair
    before = {(int(i), int(j)): (r, o) for i, j, r, o in
              zip(d0["contacts/i"], d0["contacts/j"], d0["contacts/impulse"],
                  d0["contacts/impulse_old"])}
    checked = 0
    for i, j, r in zip(d1["contacts/i"], d1["contacts/j"], d1["contacts/impulse"]):
        if (int(i), int(j)) in before and np.any(r != 0.0):
            rn, ro = before[(int(i), int(j))]
            if np.any(ro != 0.0) and np.abs(rn - ro).max() > 1e-6 * np.abs(rn).max():
                np.testing.assert_allclose(r, rn + c * (rn - ro), rtol=1e-9,
                                           atol=1e-12 * np.abs(rn).max())
                checked += 1
    assert checked > 10, checked
    sim.close()

