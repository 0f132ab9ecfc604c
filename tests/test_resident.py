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


@pytest.mark.parametrize("colouring", ["greedy", "rounds"])
@pytest.mark.parametrize("blocks", [False, True])
def test_colour_lists_hold_each_system_apart(blocks, colouring):
    """Inside each colour the items are listed system by system (cs.sys_start), so that a
    system's block reads its own items only: range (c, s) holds exactly the items of colour c
    whose bodies are system s's, and the ranges tile colour c's list (cs.start)."""
    settings = SolverSettings(max_sweeps=300, schedule="resident", colouring=colouring,
                              bond_blocks=blocks)
    sims = [batch_pour(1, settings=settings)]
    sims += [batch_pour(seed, radii=sims[0].radii(), settings=settings) for seed in (2, 3)]
    for o in sims:
        o.step(200)
        shear_wall(o)                      # bonds: bond items (or blocks) and contacts
    batch = Simulation.batch(sims)
    batch.step()
    cs, ct, bd = batch.colours, batch.contacts, batch.bonds
    ncol, nsys = batch.last.colours, batch.systems
    assert ncol > 1 and nsys == 3 and cs.systems == 3
    system = np.repeat(np.arange(nsys), sims[0].n)
    nbond, nc = int(bd.total[None]), int(ct.total[None])
    first = (np.arange(batch.n) if blocks else bd.i.to_numpy()[:nbond])
    item_system = system[np.concatenate([first, ct.i.to_numpy()[:nc]])]
    col = cs.item_colour.to_numpy()[: len(item_system)]
    order = cs.order.to_numpy()
    start, sys_start = cs.start.to_numpy(), cs.sys_start.to_numpy()
    filled = np.zeros(nsys, int)
    for c in range(ncol):
        assert sys_start[c * nsys] == start[c]
        for s in range(nsys):
            got = order[sys_start[c * nsys + s]: sys_start[c * nsys + s + 1]]
            want = np.nonzero((col == c) & (item_system == s))[0]
            assert sorted(got.tolist()) == want.tolist(), (c, s)
            filled[s] += len(want) > 0
    assert np.all(filled >= 2), filled
    assert sys_start[ncol * nsys] == start[ncol] == np.count_nonzero(col >= 0)
    for o in sims:
        o.close()
    batch.close()
