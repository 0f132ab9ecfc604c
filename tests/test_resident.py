"""The resident schedule (solver.solve_resident): the coloured schedule's colours and local
solves with all the sweeps of a step in ONE launch, one thread block per system meeting at a
block barrier after each colour (on the CPU a block is one thread).

Items of one colour share no dynamic body, so solving them in any order or at once gives the
same numbers: with one system the resident schedule must give the coloured schedule's numbers
bit for bit, sweeps included (its residual sums the same chunks in the same order). In a batch
each system converges on its own, so each must step exactly as it does alone (the greedy
colouring of a batch gives each system its colours alone). On a GPU (`pytest --arch gpu`) the
same checks hold with 256 threads per block.
"""
import dataclasses

import numpy as np
import pytest

from conftest import assert_batch_steps_as_alone
from tcd import packing, walls
from tcd.simulation import Simulation, SolverSettings

R = 0.02


def pour(seed: int, schedule: str, n: int = 120, radii=None):
    rng = np.random.default_rng(seed)
    r = packing.course_radii("surface", n, rng) * 0.5 if radii is None else rng.permutation(radii)
    x = packing.lattice_column(r, 2 * R, 0.0, rng, max_height=0.2)
    top = float(x[:, 2].max() + r.max())
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=R, name="bottom"),
          walls.cylinder((0, 0, 0), (0, 0, 1), R, (0.0, top + 0.01), friction=0.2, name="mould")]
    settings = SolverSettings(max_sweeps=300, schedule=schedule, colouring="greedy")
    return Simulation(r, x, walls=wl, friction=0.7, settings=settings,
                      domain=((-R, -R, 0.0), (R, R, top)))


def shear_wall(sim):
    """Bond the pile and move its mould sideways (bond items in the colours, a moving wall)."""
    assert sim.create_bonds(2e-4) > 20
    sim.set_walls([sim.walls[0], dataclasses.replace(sim.walls[1], motion="constant",
                                                     velocity=(0.02, 0.0, 0.0), start=sim.time)])


def assert_same_state(a, b):
    np.testing.assert_array_equal(a.positions(), b.positions())
    np.testing.assert_array_equal(a.velocities(), b.velocities())
    np.testing.assert_array_equal(a.contact_arrays()["impulse"], b.contact_arrays()["impulse"])


def test_one_system_is_the_coloured_schedule_bit_for_bit(backend):
    a, b = pour(1, "coloured"), pour(1, "resident")
    sweeps = np.array([(a.step().sweeps, b.step().sweeps) for _ in range(200)])
    assert sweeps[:, 0].max() > 5, "the pour must reach the floor within the test"
    assert a.last.colours > 1 and b.last.colours == a.last.colours
    np.testing.assert_array_equal(sweeps[:, 0], sweeps[:, 1])
    assert b.last.residual == a.last.residual
    assert_same_state(a, b)
    for sim in (a, b):
        shear_wall(sim)
    for _ in range(60):
        ra, rb = a.step(), b.step()
        assert (ra.sweeps, ra.residual) == (rb.sweeps, rb.residual)
    assert_same_state(a, b)
    assert a.bonds_intact_count() == b.bonds_intact_count() > 20
    np.testing.assert_array_equal(a.wall_force(1), b.wall_force(1))
    a.close()
    b.close()


def test_batch_steps_each_system_as_alone(backend):
    a = pour(1, "resident")
    b = pour(2, "resident", radii=a.radii())
    batch = Simulation.batch([a, b])
    sweeps = []
    for _ in range(200):
        ra, rb = a.step(), b.step()
        batch.step()
        sweeps.append((ra.sweeps, rb.sweeps, *batch.system_stats()[0]))
    sweeps = np.array(sweeps)
    assert sweeps[:, 0].max() > 5
    assert np.any(sweeps[:, 0] != sweeps[:, 1]), "the two systems must stop at different sweeps"
    np.testing.assert_array_equal(sweeps[:, 0], sweeps[:, 2])
    np.testing.assert_array_equal(sweeps[:, 1], sweeps[:, 3])
    assert batch.last.sweeps == max(sweeps[-1, 2], sweeps[-1, 3])
    x, v = batch.positions(), batch.velocities()
    for s, o in enumerate((a, b)):
        np.testing.assert_array_equal(x[batch.system_slice(s)], o.positions())
        np.testing.assert_array_equal(v[batch.system_slice(s)], o.velocities())
    for o in (a, b):
        shear_wall(o)
    assert_batch_steps_as_alone((a, b), 40)


def test_resident_schedule_refuses_the_quad_check(backend):
    with pytest.raises(ValueError, match="resident schedule .* 'Quad ' check"):
        Simulation([0.001], [[0, 0, 0.01]],
                   settings=SolverSettings(schedule="resident", convergence="quad"))
