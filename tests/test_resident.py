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

import numpy as np
import pytest

from conftest import assert_batch_steps_as_alone
from test_batch import pour as batch_pour
from test_batch import shear_wall
from tcd.simulation import Simulation, SolverSettings


def pour(seed: int, schedule: str, radii=None):
    """test_batch's pour (120 grains into a mould), greedy colouring on every backend."""
    settings = SolverSettings(max_sweeps=300, schedule=schedule, colouring="greedy")
    return batch_pour(seed, radii=radii, settings=settings)


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
    batch, sweeps = assert_batch_steps_as_alone((a, b), 200)
    assert sweeps[:, 0].max() > 5
    assert np.any(sweeps[:, 0] != sweeps[:, 1]), "the two systems must stop at different sweeps"
    assert batch.last.sweeps == sweeps[-1].max()
    for o in (a, b):
        shear_wall(o)
    assert_batch_steps_as_alone((a, b), 40)


def test_resident_schedule_refuses_the_quad_check(backend):
    with pytest.raises(ValueError, match="resident schedule .* 'Quad ' check"):
        Simulation([0.001], [[0, 0, 0.01]],
                   settings=SolverSettings(schedule="resident", convergence="quad"))
