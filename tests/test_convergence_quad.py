"""The convergence measure `convergence = "quad"`: LMGC90's 'Quad ' check (tcd/solver.py,
quad_terms) against a NumPy oracle written from its definition, and the step's stopping rule
on every schedule."""
import dataclasses
import math

import numpy as np
import pytest

from tcd import bench, laws, walls
from tcd.simulation import Simulation, SolverSettings

from conftest import schedule_settings

pytestmark = pytest.mark.f64_only    # the oracle's differences of near-equal impulses need f64


def _pile(bonded: bool, **settings):
    """27 spheres of 3 to 4 mm on a 3 x 3 x 3 lattice in a cylinder on a floor, dropped for
    0.03 s (contacts, some sliding), then, if `bonded`, the pairs closer than 0.2 mm bonded."""
    rng = np.random.default_rng(3)
    r = rng.uniform(0.003, 0.004, 27)
    g = np.arange(3) * 0.0085
    x = np.array([[a, b, 0.0045 + c] for a in g for b in g for c in g])
    x[:, :2] += rng.uniform(-4e-4, 4e-4, (27, 2))
    centre = (0.0085, 0.0085, 0.0)
    wl = [walls.plane((0, 0, 0), (0, 0, 1), friction=0.3),
          walls.cylinder(centre, (0, 0, 1), 0.016, (0.0, 0.04))]
    sim = Simulation(r, x, walls=wl, friction=0.5,
                     settings=SolverSettings(time_step=2e-4, max_sweeps=3000, **settings),
                     domain=((-0.01, -0.01, 0.0), (0.03, 0.03, 0.04)))
    sim.step(150)
    if bonded:
        assert sim.create_bonds(gap_tolerance=2e-4) > 10
    return sim


def _oracle(sim):
    """QuadDV, QuadDVR, MeanDVoR of the current state, from the fields, in NumPy."""
    n = sim.n
    v, w = sim.particles.v.to_numpy()[:n], sim.particles.w.to_numpy()[:n]
    rad = sim.particles.radius.to_numpy()[:n]
    inv_m = sim.particles.inv_mass.to_numpy()[:n]
    inv_i = sim.particles.inv_inertia.to_numpy()[:n]
    wall_v = sim.wall_fields.velocity.to_numpy()

    def rel_vel(i, j, nrm, half_gap=0.0):
        """At a contact's surfaces; at the middle of a bond's gap (half_gap past both)."""
        vi = v[i] + np.cross(w[i], (rad[i] + half_gap) * nrm)
        vj = wall_v[j - n] if j >= n else v[j] + np.cross(w[j], -(rad[j] + half_gap) * nrm)
        return vj - vi

    terms = []

    def add(r_old, r_new, nrm, wnn, wtt):
        def wmul(r):
            rn = r @ nrm
            return wnn * rn * nrm + wtt * (r - rn * nrm)
        dv = wmul(r_old - r_new)
        rm = 0.5 * (r_old + r_new)
        terms.append([dv @ dv, (dv @ dv) * (rm @ rm), rm @ dv,
                      0.5 * (wmul(r_old) @ r_old + wmul(r_new) @ r_new),
                      0.5 * (wmul(r_old) @ wmul(r_old) + wmul(r_new) @ wmul(r_new)),
                      float(rm @ rm > 0)])

    def free(u, r_old, nrm, wnn, wtt):
        un, rn_old = u @ nrm, r_old @ nrm
        return un - wnn * rn_old, (u - un * nrm) - wtt * (r_old - rn_old * nrm)

    bd = sim.bonds
    nb = int(bd.total[None])
    bond = {name: getattr(bd, name).to_numpy()[:nb]
            for name in ("i", "j", "state", "normal", "impulse", "rhs_n", "rhs_t", "cn", "ct",
                         "half_gap")}
    for b in range(nb):
        if bond["state"][b] != 0:
            continue
        i, j, nrm, r_old = int(bond["i"][b]), int(bond["j"][b]), bond["normal"][b], bond["impulse"][b]
        hg = bond["half_gap"][b]
        wnn = inv_m[i] + inv_m[j]
        wtt = wnn + (rad[i] + hg) ** 2 * inv_i[i] + (rad[j] + hg) ** 2 * inv_i[j]
        ufn, uft = free(rel_vel(i, j, nrm, hg), r_old, nrm, wnn, wtt)
        rn, rt = laws.bonded_np(ufn, uft, bond["rhs_n"][b], bond["rhs_t"][b], wnn, wtt,
                                bond["cn"][b], bond["ct"][b])
        add(r_old, rn * nrm + rt, nrm, wnn, wtt)
    ct = sim.contacts
    nc = int(ct.total[None])
    ci, cj = ct.i.to_numpy()[:nc], ct.j.to_numpy()[:nc]
    normal, impulse = ct.normal.to_numpy()[:nc], ct.impulse.to_numpy()[:nc]
    cwnn, cwtt = ct.wnn.to_numpy()[:nc], ct.wtt.to_numpy()[:nc]
    rhs, mu = ct.rhs.to_numpy()[:nc], ct.mu.to_numpy()[:nc]
    for k in range(nc):
        if cwnn[k] <= 0:
            continue
        nrm, r_old = normal[k], impulse[k]
        ufn, uft = free(rel_vel(int(ci[k]), int(cj[k]), nrm), r_old, nrm, cwnn[k], cwtt[k])
        rn, rt = laws.signorini_coulomb_np(ufn, uft, rhs[k], 1 / cwnn[k], 1 / cwtt[k], mu[k])
        add(r_old, rn * nrm + rt, nrm, cwnn[k], cwtt[k])
    s = np.sum(terms, axis=0)
    return (math.sqrt(s[0] / s[4]), math.sqrt(s[1] / s[5]) / (s[3] / s[5]), s[2] / s[3]), nb, nc


@pytest.mark.parametrize("bonded", [False, True])
def test_quad_norms_equal_the_numpy_oracle(bonded):
    """After the first sweep of a step (a sweep cap of 1, so the impulses are not converged
    and every term counts), the kernel's norms equal the oracle's."""
    sim = _pile(bonded, tolerance=1e-12)
    sim.settings = dataclasses.replace(sim.settings, max_sweeps=1)
    sim.step(1)
    (quad_dv, quad_dvr, mean_dvor), nb, nc = _oracle(sim)
    assert nc > 10 and (nb > 10) == bonded
    got = sim.quad_norms()
    assert got["QuadDV"] == pytest.approx(quad_dv, rel=1e-9)
    assert got["QuadDVR"] == pytest.approx(quad_dvr, rel=1e-9)
    assert got["MeanDVoR"] == pytest.approx(mean_dvor, rel=1e-9, abs=1e-12 * quad_dv)
    assert got["residual"] == max(abs(got["QuadDV"]), abs(got["QuadDVR"]), abs(got["MeanDVoR"]))
    # one sweep is far from the tolerance of the next test (1e-6)
    assert quad_dv > 1e-5 and sim.last.sweeps == 1


@pytest.mark.parametrize("schedule", ["serial", "partitioned", "coloured"])
@pytest.mark.parametrize("bonded", [False, True])
def test_quad_measure_stops_the_step_when_the_check_passes(schedule, bonded,
                                                           schedule_on_backend):
    """With convergence = "quad" each step stops at the first check whose norms are all below
    the tolerance: the residual it reports is the check of the state it leaves, and that
    check fails one sweep earlier (it is the first that passes)."""
    schedule_on_backend(schedule)
    tol = 1e-6
    sim = _pile(bonded, tolerance=tol, convergence="quad", **schedule_settings(schedule))
    sweeps = []
    for _ in range(5):
        state = sim.state_dict()
        rec = sim.step()
        assert rec.sweeps < sim.settings.max_sweeps and rec.residual <= tol
        assert sim.quad_norms()["residual"] == pytest.approx(rec.residual, rel=1e-9, abs=1e-18)
        sweeps.append(rec.sweeps)
        if rec.sweeps > 1:          # the same step with one sweep less has not converged
            after = sim.state_dict()
            sim.settings = dataclasses.replace(sim.settings, max_sweeps=rec.sweeps - 1)
            sim.load_state_dict(state)
            sim.step()
            assert sim.quad_norms()["residual"] > tol
            sim.settings = dataclasses.replace(sim.settings, max_sweeps=3000)
            sim.load_state_dict(after)
    assert max(sweeps) > 3


def test_quad_is_stricter_than_the_impulse_measure_on_an_impact():
    """On a pile that has just been hit (its grains still moving) the 'Quad ' check at 1e-4
    takes at least as many sweeps as the impulse measure at 1e-4 (the pour's impact step:
    docs/performance.md), and both end below their own tolerance."""
    runs = {}
    for measure in ("impulse", "quad"):
        sim = _pile(False, tolerance=1e-4, convergence=measure)
        rec = sim.step()
        runs[measure] = rec.sweeps
        assert rec.residual <= 1e-4
    assert runs["quad"] >= runs["impulse"] >= 2


def test_pour_benchmark_reports_its_convergence_measure():
    out = bench.pour(particles=60, time=0.01, convergence="quad", check_every=2)
    assert out["convergence"] == "quad" and out["check_every"] == 2
    assert out["final_residual"] <= 1e-4
