"""Batched systems (issue 8): several independent samples side by side in the same fields.

A batch must step each system exactly as it would step alone: no contact across systems, walls
acting only on their own system, each system's Gauss-Seidel converging on its own. The strongest
check is bitwise: two different pours (and then the same two bonded) stepped one by one and as a
batch give the same numbers (serial schedule, the systems' smallest radii equal).
"""
import dataclasses

import numpy as np
import pytest

from conftest import assert_batch_steps_as_alone
from tcd import packing, walls
from tcd.simulation import Simulation, SolverSettings

R = 0.02


# the serial schedule on every backend: each batched system converges on its own there (the
# coloured schedule, the GPU's default, has one convergence test for the batch: its own test)
def pour(seed: int, n: int = 120, radii=None,
         settings=SolverSettings(max_sweeps=300, schedule="serial")):
    rng = np.random.default_rng(seed)
    r = packing.course_radii("surface", n, rng) * 0.5 if radii is None else rng.permutation(radii)
    x = packing.lattice_column(r, 2 * R, 0.0, rng, max_height=0.2)
    top = float(x[:, 2].max() + r.max())
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=R, name="bottom"),
          walls.cylinder((0, 0, 0), (0, 0, 1), R, (0.0, top + 0.01), friction=0.2, name="mould")]
    return Simulation(r, x, walls=wl, friction=0.7, settings=settings,
                      domain=((-R, -R, 0.0), (R, R, top)))


def shear_wall(sim):
    """Bond a pour and move its mould sideways from now on."""
    assert sim.create_bonds(2e-4) > 20
    sim.set_walls([sim.walls[0], dataclasses.replace(sim.walls[1], motion="constant",
                                                     velocity=(0.02, 0.0, 0.0), start=sim.time)])


@pytest.fixture(scope="module")
def pair(backend):
    """Two different pours with the same radii (so the same smallest grain)."""
    a = pour(1)
    b = pour(2, radii=a.radii())
    return a, b


def test_batch_steps_each_system_as_alone(pair, precision):
    a, b = pair
    batch, sweeps = assert_batch_steps_as_alone((a, b), 200)
    assert batch.systems == 2 and batch.n == a.n + b.n
    assert sweeps[:, 0].max() > 5, "the pours must reach the floor within the test"
    # each system's walls felt only its own particles
    for s, o in enumerate((a, b)):
        for m, k in enumerate(batch.system_walls(s)):
            np.testing.assert_array_equal(batch.wall_force(k), o.wall_force(m))

    # now bonded: bond both, batch again, step both ways with a moving wall
    for o in (a, b):
        shear_wall(o)
    batch, _ = assert_batch_steps_as_alone((a, b), 60)
    assert batch.bonds_intact_count() == a.bonds_intact_count() + b.bonds_intact_count()


def test_split_gives_back_each_system(pair):
    a, b = pair
    batch = Simulation.batch([a, b])
    batch.step()
    a.step()
    b.step()
    for o, part in zip((a, b), batch.split()):
        mine = o.state_dict()
        assert [dataclasses.replace(w) for w in part.pop("walls")] == o.walls
        assert set(part) == set(mine)
        for key, value in mine.items():
            np.testing.assert_array_equal(part[key], value, err_msg=key)


def test_system_views_read_each_field_once_per_step(pair):
    """The views of `tcd run --batch` (SystemView.all) give each system's numbers as it has
    them alone, and read each of the batch's fields once per step for all the views."""
    from tcd.simulation import SystemView
    a, b = pair
    batch = Simulation.batch([a, b])
    views = SystemView.all(batch)
    for _ in range(2):
        batch.step()
        recs = [o.step() for o in (a, b)]
        reads = views[0].reads
        assert all(view.reads is reads for view in views)
        counts = [reads.reads]
        for view, o, rec in zip(views, (a, b), recs):
            assert view.solver_stats() == (rec.sweeps, rec.residual)
            assert view.contact_count() == rec.contacts
            assert view.bonds_state_counts() == o.bonds_state_counts()
            for m in range(len(o.walls)):
                np.testing.assert_array_equal(view.wall_force(m), o.wall_force(m))
            for name in ("positions", "velocities", "angular_velocities", "radii"):
                np.testing.assert_array_equal(getattr(view, name)(), getattr(o, name)(),
                                              err_msg=name)
            assert view.kinetic_energy() == o.kinetic_energy()
            counts.append(reads.reads)
        # x, v, w, radius, wall forces, bond starts, bond states, contact starts, solver stats:
        # read once each by the first view in this step, and not again by the second
        assert np.diff(counts).tolist() == [9, 0]
    # a slice handed out is the caller's: changing it leaves the next view's read alone
    views[0].positions()[:] = 0.0
    np.testing.assert_array_equal(views[0].positions(), a.positions())


@pytest.mark.f64_only   # compares two runs of the same code: once, in f64, is enough
def test_batch_carries_the_extrapolated_warm_start(backend):
    """With warm_start_extrapolation the previous impulses of every bond and contact travel
    into the batch and out of it: each system steps as alone, bit for bit."""
    settings = SolverSettings(max_sweeps=300, schedule="serial", warm_start_extrapolation=0.5)
    a = pour(1, settings=settings)
    b = pour(2, radii=a.radii(), settings=settings)
    for o in (a, b):
        o.step(200)
        assert o.create_bonds(2e-4) > 20
        o.step(5)
    batch = Simulation.batch([a, b])
    for _ in range(25):
        ra, rb = a.step(), b.step()
        batch.step()
        np.testing.assert_array_equal(batch.system_stats()[0], [ra.sweeps, rb.sweeps])
    for o, part in zip((a, b), batch.split()):
        mine = o.state_dict()
        for key in ("particles/v", "bonds/impulse", "bonds/impulse_prev", "contacts/impulse",
                    "contacts/impulse_old"):
            np.testing.assert_array_equal(part[key], mine[key], err_msg=key)


def test_superimposed_systems_never_touch(backend):
    """Two copies of one pour in the same place: every contact stays inside a system, each
    system's contact set is that of the pour alone (the brute-force pairs within the alert
    distance), and a wall tagged with one system never touches the other."""
    a = pour(3)
    b = pour(3)
    batch = Simulation.batch([a, b])
    for _ in range(100):
        batch.step()
        a.step()
    c = batch.contact_arrays()
    system = np.repeat([0, 1], a.n)
    n = batch.n
    pp = c["j"] < n
    assert np.all(system[c["i"][pp]] == system[c["j"][pp]])
    wall_system = np.array([w.system for w in batch.walls])
    assert np.all(wall_system[c["j"][~pp] - n] == system[c["i"][~pp]])
    mine = a.contact_arrays()
    for s in (0, 1):
        sel = system[c["i"]] == s
        off = s * a.n
        j = np.where(c["j"][sel] < n, c["j"][sel] - off, c["j"][sel] - n - 2 * s + a.n)
        np.testing.assert_array_equal(c["i"][sel] - off, mine["i"])
        np.testing.assert_array_equal(j, mine["j"])
    # brute force: every particle pair of system 0 with a gap below the alert distance is a contact
    x, r = a.positions(), a.radii()
    d = np.linalg.norm(x[:, None] - x[None], axis=2) - r[:, None] - r[None]
    i, j = np.nonzero(np.triu(d < a.alert, 1))
    found = set(zip(mine["i"].tolist(), mine["j"].tolist()))
    assert set(zip(i.tolist(), j.tolist())) <= found


def test_batch_rejects_mismatched_systems():
    """Its own simulations: it used `pair`, which another test of this file steps, so under
    `--dist load` (the GPU check) a worker could hand it two unstepped pours and the time
    mismatch was not there to refuse."""
    a = pour(1)
    b = pour(2, radii=a.radii())
    other = pour(4, n=20, settings=SolverSettings(max_sweeps=300, time_step=1e-4))
    with pytest.raises(ValueError, match="differs from simulation 0 in settings"):
        Simulation.batch([pour(5, n=20), other])
    stepped = pour(3)                   # the size class the other tests step: no new compile
    stepped.step()
    with pytest.raises(ValueError, match="differs from simulation 0 in time"):
        Simulation.batch([pour(5), stepped])
    with pytest.raises(ValueError, match="at least one"):
        Simulation.batch([])
    batch = Simulation.batch([a, b])
    with pytest.raises(ValueError, match="already a batch"):
        Simulation.batch([batch, a])
    with pytest.raises(ValueError, match="system 2"):
        batch.set_walls(batch.walls + [walls.plane((0, 0, 0.1), (0, 0, -1), system=2)])
    with pytest.raises(ValueError, match="no system 5"):
        batch.system_slice(5)
    with pytest.raises(ValueError, match="never decrease"):
        Simulation([0.001] * 3, [[0, 0, 0.01], [0, 0, 0.02], [0, 0, 0.03]], system=[0, 1, 0])
    with pytest.raises(ValueError, match="system must be an integer"):
        walls.plane((0, 0, 0), (0, 0, 1), system=-2)


def test_coloured_schedule_batches_too(backend):
    """The GPU's schedule (coloured Gauss-Seidel, one convergence test over the whole batch) on
    the CPU: the systems stay apart, and each ends within a hundredth of the smallest radius of
    where it goes alone (the batch may sweep more than a system alone needs)."""
    settings = SolverSettings(max_sweeps=300, schedule="coloured")
    a = pour(1, settings=settings)
    b = pour(2, radii=a.radii(), settings=settings)
    batch = Simulation.batch([a, b])
    for _ in range(120):
        a.step()
        b.step()
        batch.step()
    assert batch.last.colours > 1 and batch.last.sweeps > 1
    sweeps, residual = batch.system_stats()
    assert np.all(sweeps == batch.last.sweeps) and np.all(residual <= settings.tolerance)
    x = batch.positions()
    for s, o in enumerate((a, b)):
        assert np.abs(x[batch.system_slice(s)] - o.positions()).max() < 0.01 * a.r_min
    c = batch.contact_arrays()
    system = np.repeat([0, 1], a.n)
    pp = c["j"] < batch.n
    assert np.all(system[c["i"][pp]] == system[c["j"][pp]])
