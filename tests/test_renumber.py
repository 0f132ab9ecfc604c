"""Renumbering the particles (`Simulation.renumber`, the shear stage's `renumber = true`).

A renumbered simulation is the same physical state under other particle indices: every
particle keeps its position, velocities, radius, layer and mass, every contact its impulse
history (listed again in canonical order, the impulse's sign following the pair's order), and
each particle its index in the sample (`sample_index`), which state files, batches and splits
carry. Only the Gauss-Seidel's visiting order changes, so a renumbered run agrees with the
original to the solver's tolerance, not bit for bit.
"""
import dataclasses

import numpy as np
import pytest

from tcd import packing, walls
from tcd.simulation import Simulation, SolverSettings

R = 0.02


def pile(seed=5, n=90, tolerance=1e-4, max_sweeps=2000):
    rng = np.random.default_rng(seed)
    r = packing.course_radii("surface", n, rng) * 0.5
    x = packing.lattice_column(r, 2 * R, 0.0, rng, max_height=0.2)
    top = float(x[:, 2].max() + r.max())
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=R, name="bottom"),
          walls.cylinder((0, 0, 0), (0, 0, 1), R, (0.0, top + 0.01), friction=0.2, name="mould")]
    settings = SolverSettings(max_sweeps=max_sweeps, schedule="serial", tolerance=tolerance)
    return Simulation(r, x, walls=wl, friction=0.7, settings=settings,
                      domain=((-R, -R, 0.0), (R, R, top)))


@pytest.fixture(scope="module")
def settled(backend):
    """A small pour stepped until its grains rest on the floor and on each other."""
    sim = pile()
    sim.step(400)
    assert len(sim.contact_arrays()["i"]) > sim.n
    return sim


def _pairs(d, index):
    """{(sample index of one body, of the other or a wall): impulse on the second} of a state."""
    n = len(d["particles/x"])
    out = {}
    for i, j, imp in zip(d["contacts/i"], d["contacts/j"], d["contacts/impulse"]):
        a = int(index[i])
        b = int(index[j]) if j < n else ("wall", int(j - n))
        if j < n and b < a:
            a, b, imp = b, a, -imp
        out[(a, b)] = imp
    return out


def test_renumbered_state_is_the_same_state_under_other_indices(settled):
    sim = settled
    x = sim.positions()
    order = np.argsort(x[:, 0], kind="stable")
    new = sim.renumber(order)
    try:
        assert new.renumbered and not sim.renumbered
        np.testing.assert_array_equal(new.sample_index, order)
        d, e = sim.state_dict(), new.state_dict()
        for key in ("x", "v", "w", "radius", "layer", "inv_mass", "inv_inertia", "f_ext"):
            np.testing.assert_array_equal(e["particles/" + key], d["particles/" + key][order], key)
        np.testing.assert_array_equal(e["particles/sample_index"], order)
        assert "particles/sample_index" not in d
        # every contact, with its impulse, under the new indices; canonical order
        ci, cj = e["contacts/i"], e["contacts/j"]
        assert np.all((cj >= new.n) | (ci < cj))
        key = ci.astype(np.int64) * (new.n + 64) + cj
        assert np.all(np.diff(key) > 0)
        np.testing.assert_array_equal(e["contacts/start"], np.searchsorted(ci, np.arange(new.n + 1)))
        before, after = _pairs(d, np.arange(sim.n)), _pairs(e, order)
        assert before.keys() == after.keys() and len(before) == len(sim.contact_arrays()["i"])
        for k in before:
            np.testing.assert_array_equal(before[k], after[k])
        np.testing.assert_array_equal(e["walls/force"], d["walls/force"])
        assert new.time == sim.time and new.step_index == sim.step_index
        # the state is unchanged by renumbering back
        back = new.renumber(np.argsort(order))
        try:
            assert not back.renumbered
            f = back.state_dict()
            assert f.keys() == d.keys()
            for k in d:
                np.testing.assert_array_equal(f[k], d[k], k)
        finally:
            back.close()
    finally:
        new.close()


def test_renumbered_pile_steps_as_the_original_to_the_tolerance(backend, precision):
    """Settled at a tight tolerance, the same pile under reversed indices (the visiting order
    reversed) keeps carrying its weight on the floor and moves as the original within what the
    tolerance allows."""
    tol = 1e-9 if precision == "f64" else 1e-5
    a = pile(seed=7, n=60)
    a.step(1500)
    a.settings = dataclasses.replace(a.settings, tolerance=tol, max_sweeps=20000)
    order = np.arange(a.n)[::-1].copy()
    b = a.renumber(order)
    try:
        for _ in range(20):
            a.step()
            b.step()
        g = 9.81
        weight = float(np.sum(4.0 / 3.0 * np.pi * a.radii() ** 3 * a.density)) * g
        for o in (a, b):        # floor and mould (its friction) carry the weight
            assert o.wall_force(0)[2] + o.wall_force(1)[2] == pytest.approx(-weight, rel=1e-2)
        for k in (0, 1):
            np.testing.assert_allclose(b.wall_force(k), a.wall_force(k),
                                       atol=(1e-6 if precision == "f64" else 1e-3) * weight)
        xa, xb = a.positions(), b.positions()
        scale = 1e-9 if precision == "f64" else 1e-6
        assert np.abs(xb - xa[order]).max() < scale
    finally:
        b.close()
        a.close()


def test_sample_index_survives_a_state_round_trip_a_batch_and_a_split(settled):
    sim = settled
    order = np.random.default_rng(3).permutation(sim.n)
    new = sim.renumber(order)
    other = pile(seed=8, n=sim.n)
    other.time = new.time          # a batch has one clock
    try:
        d = new.state_dict()
        fresh = Simulation(d["particles/radius"], d["particles/x"], walls=new.walls,
                           settings=new.settings, domain=new.domain)
        try:
            assert not fresh.renumbered
            fresh.load_state_dict(d)
            np.testing.assert_array_equal(fresh.sample_index, order)
        finally:
            fresh.close()
        batch = Simulation.batch([other, new])
        try:
            np.testing.assert_array_equal(batch.sample_index[batch.system_slice(1)], order)
            np.testing.assert_array_equal(batch.sample_index[batch.system_slice(0)], np.arange(other.n))
            a, b = batch.split()
            assert "particles/sample_index" not in a
            np.testing.assert_array_equal(b["particles/sample_index"], order)
        finally:
            batch.close()
    finally:
        other.close()
        new.close()


def test_renumber_refuses_what_it_cannot_do(settled):
    sim = settled
    with pytest.raises(ValueError, match="permutation"):
        sim.renumber(np.zeros(sim.n, np.int64))
    with pytest.raises(ValueError, match="permutation"):
        sim.renumber(np.arange(sim.n - 1))
    d = sim.state_dict()
    d["particles/sample_index"] = np.zeros(sim.n, np.int32)
    with pytest.raises(ValueError, match="sample_index of system 0 is not a permutation"):
        sim.load_state_dict(d)
    bonded = pile(seed=9, n=40)
    try:
        bonded.step(200)
        assert bonded.create_bonds(2e-4) > 0
        with pytest.raises(ValueError, match="before creating bonds"):
            bonded.renumber(np.arange(bonded.n))
        batch = Simulation.batch([pile(seed=10, n=30), pile(seed=11, n=30)])
        with pytest.raises(ValueError, match="one system"):
            batch.renumber(np.arange(batch.n))
        batch.close()
    finally:
        bonded.close()


def test_a_simulation_that_never_stepped_gives_empty_contact_ranges(settled):
    """A simulation that never stepped has no contact list, but its pooled contact buffer may
    hold the start table of a simulation that did (here `settled`'s, closed and its fields
    pooled). state_dict gave that old table: merged into a batch with a stepped system, its
    offsets pointed into the other system's contacts (session 47's CI: the batch refused its
    own merged state). Now its ranges are empty, and a batch of the two loads."""
    stepped = settled.renumber(np.arange(settled.n))      # a copy with `settled`'s contacts
    old = settled.renumber(np.arange(settled.n))
    assert np.any(old.state_dict()["contacts/start"] > 0)
    old.close()                                             # its buffer, with a table, pooled
    fresh = pile(seed=9, n=settled.n)
    fresh.time = stepped.time
    try:
        d = fresh.state_dict()
        assert len(d["contacts/i"]) == 0
        np.testing.assert_array_equal(d["contacts/start"], np.zeros(fresh.n + 1))
        batch = Simulation.batch([fresh, stepped])
        try:
            e = batch.state_dict()
            start = e["contacts/start"]
            assert np.all(start[:fresh.n + 1] == 0) and np.all(np.diff(start) >= 0)
            assert start[-1] == len(e["contacts/i"]) == len(stepped.contact_arrays()["i"])
        finally:
            batch.close()
    finally:
        fresh.close()
        stepped.close()
