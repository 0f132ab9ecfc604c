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


def pour(seed: int, schedule: str, radii=None, **solver):
    """test_batch's pour (120 grains into a mould), greedy colouring on every backend."""
    settings = SolverSettings(max_sweeps=300, schedule=schedule, colouring="greedy", **solver)
    return batch_pour(seed, radii=radii, settings=settings)


def assert_same_state(a, b):
    np.testing.assert_array_equal(a.positions(), b.positions())
    np.testing.assert_array_equal(a.velocities(), b.velocities())
    np.testing.assert_array_equal(a.contact_arrays()["impulse"], b.contact_arrays()["impulse"])


def assert_close_state(a, b, rel):
    """Positions, velocities, impulses and the shear wall's force equal to `rel` of each
    array's largest magnitude."""
    for get in (lambda s: s.positions(), lambda s: s.velocities(),
                lambda s: s.contact_arrays()["impulse"], lambda s: s.wall_force(1)):
        ya, yb = np.asarray(get(a)), np.asarray(get(b))
        np.testing.assert_allclose(ya, yb, rtol=0, atol=rel * np.abs(ya).max())


def test_one_system_is_the_coloured_schedule_bit_for_bit(backend):
    """Bit for bit on the CPU. On a GPU the bonded steps are compared to 1e-9 only: the two
    schedules' kernels are compiled apart, and with fast math the compiler may fuse a
    multiply-add in one and not in the other (H200, session 38: the 200 pour steps were equal
    bit for bit; the first bonded step took 21 sweeps in both, and its residual differed from
    the 13th digit on, 9.712922789086598e-05 against 9.712922789086988e-05)."""
    exact = backend[0] == "cpu"
    a = pour(1, "coloured")
    b = pour(1, "resident", acceleration="none")
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
        assert ra.sweeps == rb.sweeps
        if exact:
            assert ra.residual == rb.residual
        else:
            assert ra.residual == pytest.approx(rb.residual, rel=1e-9)
    assert a.bonds_intact_count() == b.bonds_intact_count() > 20
    if exact:
        assert_same_state(a, b)
        np.testing.assert_array_equal(a.wall_force(1), b.wall_force(1))
    else:
        assert_close_state(a, b, 1e-9)
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


@pytest.mark.parametrize("blocks, colouring", [(False, "greedy"), (True, "rounds")])
def test_colour_lists_hold_each_system_apart(blocks, colouring):
    """Inside each colour the items are listed system by system (cs.sys_start), so that a
    system's block reads its own items only: range (c, s) holds exactly the items of colour c
    whose bodies are system s's, and the ranges tile colour c's list (cs.start)."""
    settings = SolverSettings(max_sweeps=300, schedule="resident", colouring=colouring,
                              bond_blocks=blocks)
    sims = [batch_pour(1, settings=settings)]
    sims += [batch_pour(2, radii=sims[0].radii(), settings=settings)]
    for o in sims:
        o.step(200)
        shear_wall(o)                      # bonds: bond items (or blocks) and contacts
    batch = Simulation.batch(sims)
    batch.step()
    cs, ct, bd = batch.colours, batch.contacts, batch.bonds
    ncol, nsys = batch.last.colours, batch.systems
    assert ncol > 1 and nsys == 2 and cs.systems == 2
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


@pytest.mark.parametrize("schedule, acceleration, momentum", [
    ("resident", "none", ""), ("resident", "nncg", "bodies"), ("resident", "nncg", "items"),
    ("serial", "nncg", "")])
def test_velocities_are_the_free_ones_plus_the_impulses(backend, tol, monkeypatch, schedule,
                                                       acceleration, momentum):
    """After every step, v = v_free + M^-1 H^T R over the step's contacts and bonds, in
    translation and rotation: NNCG's momentum moves each impulse and its bodies by the same
    amount (on the resident schedule by default a pass over the items for the impulses and
    one over the particles for the bodies, solver.body_momentum, which never reads the items;
    with TCD_RESIDENT_MOMENTUM=items and on the serial schedule each item moves its bodies),
    and the step ends on its impulses' own velocities."""
    monkeypatch.setenv("TCD_RESIDENT_MOMENTUM", momentum)
    sim = pour(1, schedule, acceleration=acceleration)
    assert sim._resident_accel() == {"": 2 * (schedule == "resident" and acceleration == "nncg"),
                                     "bodies": 2, "items": 1}[momentum]
    sim.step(200)
    shear_wall(sim)
    n, r = sim.n, sim.radii()
    m = 2600.0 * 4.0 / 3.0 * np.pi * r**3
    inertia = 0.4 * m * r**2
    h, g = sim.settings.time_step, np.asarray(sim.settings.gravity)
    bonded = 0
    for _ in range(6):
        x0, v0, w0 = sim.positions(), sim.velocities(), sim.angular_velocities()
        d0 = sim.state_dict()
        intact = d0["bonds/state"] == 0
        bi, bj = d0["bonds/i"][intact], d0["bonds/j"][intact]
        sim.step()
        dv, dw = np.zeros((n, 3)), np.zeros((n, 3))

        def receive(i, j, normal, impulse, half_gap=0.0):     # solver.apply_impulse_at
            # at a contact's surfaces; at the middle of a bond's gap (solver.bond_arms)
            np.add.at(dv, i, -impulse)
            np.add.at(dw, i, -np.cross((r[i] + half_gap)[:, None] * normal, impulse))
            pp = j < n
            hj = half_gap[pp] if np.ndim(half_gap) else half_gap
            np.add.at(dv, j[pp], impulse[pp])
            np.add.at(dw, j[pp], np.cross(-(r[j[pp]] + hj)[:, None] * normal[pp], impulse[pp]))
        c = sim.contact_arrays()
        receive(c["i"], c["j"], c["normal"], c["impulse"])
        bn = x0[bj] - x0[bi]
        dist = np.linalg.norm(bn, axis=1)
        bn /= dist[:, None]
        rb = sim.state_dict()["bonds/impulse"][intact]
        receive(bi, bj, bn, rb, 0.5 * (dist - r[bi] - r[bj]))
        bonded += np.count_nonzero(np.abs(rb).sum(axis=1) > 0)
        scale = max(np.abs(v0).max(), np.abs(dv / m[:, None]).max())
        np.testing.assert_allclose(sim.velocities(), v0 + h * g + dv / m[:, None],
                                   rtol=0, atol=10 * tol * scale)
        # scaled like the velocities: in f32 the momentum moves the bodies and the items
        # apart by the rounding of their sums, at the scale of the spins themselves
        # (session 46: 9.4e-3 rad/s on a grain among grains spinning at 100 rad/s)
        scale = max(np.abs(w0).max(), np.abs(dw / inertia[:, None]).max())
        np.testing.assert_allclose(sim.angular_velocities(), w0 + dw / inertia[:, None],
                                   rtol=0, atol=10 * tol * scale)
    assert bonded > 100 and sim.last.sweeps > 3
    sim.close()


def test_nncg_needs_fewer_sweeps_on_the_resident_schedule(backend):
    """The NNCG momentum on the resident schedule cuts the sweeps of a pour and of its bonded
    shear, to the same tolerance (sweep counts, not times: seed-1 shear of the shipped sample,
    0.02 s, 28.5 mean sweeps against 70.3; docs/performance.md)."""
    runs = {a: pour(1, "resident", acceleration=a) for a in ("none", "nncg")}
    sweeps = {a: [sim.step().sweeps for _ in range(200)] for a, sim in runs.items()}
    for sim in runs.values():
        shear_wall(sim)
    bonded = {a: [sim.step().sweeps for _ in range(40)] for a, sim in runs.items()}
    assert sum(sweeps["nncg"]) < 0.8 * sum(sweeps["none"]), sweeps
    assert sum(bonded["nncg"]) < 0.8 * sum(bonded["none"]), bonded
    for sim in runs.values():
        assert sim.last.residual <= sim.settings.tolerance
        sim.close()


@pytest.mark.parametrize("text, threads", [("", 256), ("64", 64), ("1024", 1024)])
def test_gpu_block_size_is_read_from_the_environment(text, threads):
    from tcd import solver
    assert solver.resident_gpu_threads(text) == threads


@pytest.mark.parametrize("text", ["0", "100", "2048", "many", "-32"])
def test_a_bad_gpu_block_size_is_refused(text):
    from tcd import solver
    with pytest.raises(ValueError, match="TCD_RESIDENT_THREADS=.*multiple of 32 from 32 to 1024"):
        solver.resident_gpu_threads(text)


@pytest.mark.parametrize("text, accel", [("", 2), ("bodies", 2), ("items", 1)])
def test_resident_momentum_is_read_from_the_environment(text, accel):
    from tcd import solver
    assert solver.resident_momentum(text) == accel


def test_a_bad_resident_momentum_is_refused():
    from tcd import solver
    with pytest.raises(ValueError, match="TCD_RESIDENT_MOMENTUM='colours': expected one of "
                                         "bodies, items"):
        solver.resident_momentum("colours")


def test_only_the_bodies_momentum_holds_the_per_particle_scratch(backend, monkeypatch):
    """solver.body_momentum's four vectors per particle live in the colour set, sized to the
    particles only where that momentum runs (96 B per particle in f64): elsewhere one slot."""
    sizes = {}
    for momentum, acceleration in (("bodies", "nncg"), ("items", "nncg"), ("bodies", "none")):
        monkeypatch.setenv("TCD_RESIDENT_MOMENTUM", momentum)
        sim = pour(1, "resident", acceleration=acceleration)
        sim.step()
        sizes[momentum, acceleration] = sim.colours.dir_v.shape[0]
        sim.close()
    assert sizes["bodies", "nncg"] >= 120 and sizes["items", "nncg"] == sizes["bodies", "none"] == 1


@pytest.mark.parametrize("schedule, order, acceleration", [
    ("serial", "symmetric", "nncg"), ("coloured", "forward", "none"),
    ("resident", "forward", "nncg")])
def test_benchmarks_report_the_sweep_order_and_momentum_each_schedule_runs(
        backend, schedule, order, acceleration):
    """The coloured and resident schedules sweep their colours forward whatever sweep_order
    says, and the coloured one is always plain: `tcd bench` reports what ran."""
    sim = Simulation([0.001], [[0, 0, 0.01]], settings=SolverSettings(schedule=schedule))
    assert (sim.sweep_order_used, sim.acceleration_used) == (order, acceleration)
    assert sim.resident_block == ({"threads": 1 if backend[0] == "cpu" else 256,
                                   "momentum": "bodies"} if schedule == "resident" else {})
    sim.close()


@pytest.mark.parametrize("momentum, acceleration, reported", [
    ("items", "nncg", "items"), ("", "none", "none")])
def test_the_resident_block_is_reported_as_run(backend, monkeypatch, momentum, acceleration,
                                               reported):
    monkeypatch.setenv("TCD_RESIDENT_MOMENTUM", momentum)
    sim = Simulation([0.001], [[0, 0, 0.01]],
                     settings=SolverSettings(schedule="resident", acceleration=acceleration))
    assert sim.resident_block["momentum"] == reported
    sim.close()


# --- session 43's mutation audit of the schedules, batching and the grid ------------------
def test_check_every_on_the_coloured_and_resident_schedules():
    """check_every = 3 on the coloured schedule and the resident one (one system, no momentum:
    the coloured schedule's numbers): every step ends on a multiple of 3 sweeps, the same in
    both, same state. Kills: either loop testing (sweeps + 1) % check_every."""
    a = pour(1, "coloured", check_every=3)
    b = pour(1, "resident", acceleration="none", check_every=3)
    sweeps = np.array([(a.step().sweeps, b.step().sweeps) for _ in range(150)])
    assert sweeps.max() > 5
    assert np.all((sweeps % 3 == 0) | (sweeps == 300))
    np.testing.assert_array_equal(sweeps[:, 0], sweeps[:, 1])
    assert_same_state(a, b)
    a.close()
    b.close()

