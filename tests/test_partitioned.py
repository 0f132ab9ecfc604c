"""The partitioned schedule: the serial Gauss-Seidel split over P CPU threads (tcd/partitioned.py).

Its numbers must depend on P only (never on thread timing or on how many threads Taichi has),
with one part it is the serial sweep itself, and its lists must hold every item once with the
interior items inside their slab.
"""
import functools
import pathlib

import numpy as np
import pytest

from tcd import packing, walls
from tcd.simulation import Simulation, SolverSettings

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def cpu_only(backend):
    if backend[0] != "cpu":
        pytest.skip("the partitioned schedule runs on the CPU (the GPU has the coloured one)")


def pour(n=150, steps=300, seed=3, diameter=0.06, **settings):
    """A column of n binder grains (half size) poured into a cylinder (the grains reach the
    floor and pile up within the steps)."""
    rng = np.random.default_rng(seed)
    r = packing.course_radii("binder", n, rng) * 0.5
    x = packing.lattice_column(r, diameter, 0.0, rng)
    wl = [walls.plane((0, 0, 0), (0, 0, 1)),
          walls.cylinder((0, 0, 0), (0, 0, 1), diameter / 2, (0, 1))]
    sim = Simulation(r, x, walls=wl, settings=SolverSettings(**settings),
                     domain=((-0.03, -0.03, 0), (0.03, 0.03, 0.4)))
    sweeps = [sim.step().sweeps for _ in range(steps)]
    return sim, np.array(sweeps)


@pytest.mark.parametrize("order", ["forward", "symmetric"])
def test_one_part_is_the_serial_gauss_seidel_bit_for_bit(precision, order):
    a, sa = pour(schedule="serial", sweep_order=order)
    b, sb = pour(schedule="partitioned", threads=1, sweep_order=order)
    assert sa.max() > 20                      # the pour has impacts: many sweeps per step
    assert np.array_equal(sa, sb)
    assert np.array_equal(a.positions(), b.positions())
    assert np.array_equal(a.velocities(), b.velocities())
    assert np.array_equal(a.contact_arrays()["impulse"], b.contact_arrays()["impulse"])
    a.close()
    b.close()


@pytest.mark.parametrize("threads", [2, 3])
def test_same_parts_same_numbers_and_lists_are_sound(threads):
    """Two runs with the same P give the same numbers (whatever the threads' timing; P = 3 is
    more parts than this machine's cores, so units wait for a free thread); every contact is
    listed once, an interior contact's bodies lie in its slab, and the partition is used
    (interior lists not empty)."""
    a, sa = pour(schedule="partitioned", threads=threads)
    b, sb = pour(schedule="partitioned", threads=threads)
    assert np.array_equal(sa, sb)
    assert np.array_equal(a.positions(), b.positions())
    assert np.array_equal(a.velocities(), b.velocities())
    pt, n = a.partition, a.n
    part = pt.part.to_numpy()[:n]
    assert part.min() == 0 and part.max() == threads - 1
    # slabs across one axis: ordered along it, one slab after the other
    x = a.positions()
    assert any(all(x[part == k, ax].max() <= x[part == k + 1, ax].min()
                   for k in range(threads - 1)) for ax in range(3))
    cstart = pt.cstart.to_numpy()[: threads + 2]
    order = pt.corder.to_numpy()[: cstart[-1]]
    c = a.contact_arrays()
    assert sorted(order.tolist()) == list(range(len(c["i"])))
    for k in range(threads):
        inside = order[cstart[k]:cstart[k + 1]]
        assert len(inside) > 0
        i, j = c["i"][inside], c["j"][inside]
        assert np.all(part[i] == k) and np.all((j >= n) | (part[np.minimum(j, n - 1)] == k))
    boundary = order[cstart[threads]:]
    i, j = c["i"][boundary], c["j"][boundary]
    assert np.all((j < n) & (part[i] != part[np.minimum(j, n - 1)]))
    a.close()
    b.close()


def alternations(part):
    return int(np.count_nonzero(part[1:] != part[:-1]))


def test_slabs_are_cut_across_the_axis_where_they_alternate_least_in_memory():
    """A flat bed 20 x 4 x 3 spheres, numbered layer by layer (z slowest): its longest extent
    is x, but slabs across x would alternate twice per row of 20 (two threads writing the same
    cache lines: false sharing), while slabs across z are contiguous in memory. The schedule
    picks z, with one alternation of the particles and every list still sound."""
    d = 0.004
    ix, iy, iz = np.meshgrid(np.arange(20), np.arange(4), np.arange(3), indexing="ij")
    order = np.lexsort((ix.ravel(), iy.ravel(), iz.ravel()))      # z slowest, then y, then x
    x = (np.stack([ix.ravel(), iy.ravel(), iz.ravel()], axis=1)[order] + 0.5) * d
    r = np.full(len(x), 0.5 * d)
    wl = [walls.plane((0, 0, 0), (0, 0, 1))]
    sim = Simulation(r, x, walls=wl, settings=SolverSettings(schedule="partitioned", threads=2),
                     domain=((0, 0, 0), (20 * d, 4 * d, 3 * d)))
    sim.step()
    n = sim.n
    part = sim.partition.part.to_numpy()[:n]
    assert part.min() == 0 and part.max() == 1
    z = sim.positions()[:, 2]
    assert z[part == 0].max() < z[part == 1].min()               # slabs across z
    assert alternations(part) == 1
    # across the longest extent (x, the earlier rule) the slabs alternate twice per row
    xs = sim.positions()[:, 0]
    assert alternations((xs > np.median(xs)).astype(int)) > 20
    cstart = sim.partition.cstart.to_numpy()[:4]
    c = sim.contact_arrays()
    assert cstart[-1] == len(c["i"]) and cstart[0] < cstart[1] < cstart[2]
    sim.close()


def test_numbers_do_not_depend_on_the_number_of_threads(other_side):
    """P = 2 parts run by one Taichi thread give the numbers of the same P = 2 run by a pool of
    two threads: the test process runs one side (one thread when the test workers run inline,
    tests/conftest.py), a child process the other."""
    child = other_side("""
        from test_partitioned import pour
        sim, sweeps = pour(steps=150, schedule="partitioned", threads=2)
        print(json.dumps({"x": sim.positions().tolist(), "sweeps": sweeps.tolist()}))
    """)
    sim, sweeps = pour(steps=150, schedule="partitioned", threads=2)
    assert child["sweeps"] == sweeps.tolist()
    assert np.array_equal(np.array(child["x"]), sim.positions())
    sim.close()


@functools.lru_cache(maxsize=1)
def pile():
    """The settled 60-grain pile of the bonded-cluster tests (state dict, radii), made once."""
    base, _ = pour(n=60, steps=2500, seed=5, diameter=0.025, max_sweeps=400)
    state, r = base.state_dict(), base.radii()
    base.close()
    return state, r


def bonded_cluster(variants):
    """A bonded pile carried sideways by its moving mould at 10 mm/s, 3 steps at tolerance 1e-7,
    once per SolverSettings variant (a dict); (velocities, bond impulses) of each."""
    state, r = pile()
    results = []
    for settings in variants:
        # the pile's own walls, the mould now moving sideways at 10 mm/s
        wl = [walls.plane((0, 0, 0), (0, 0, 1)),
              walls.cylinder((0, 0, 0), (0, 0, 1), 0.0125, (0, 1), motion="constant",
                             velocity=(0.01, 0, 0))]
        sim = Simulation(r, state["particles/x"], walls=wl,
                         settings=SolverSettings(tolerance=1e-7, max_sweeps=200000, threads=2,
                                                 **settings),
                         domain=((-0.05, -0.05, 0), (0.05, 0.05, 0.2)))
        sim.load_state_dict({**state, "walls/force": np.zeros((2, 3))})
        assert sim.create_bonds(gap_tolerance=5e-4) > 100
        for _ in range(3):
            rec = sim.step()
            assert rec.residual <= 1e-7 and rec.bonds_intact > 100
        results.append((sim.velocities(), sim.state_dict()["bonds/impulse"]))
        sim.close()
    return results


def bond_bound(precision: str) -> float:
    """Largest bond impulse difference between two schedules or sweep orders, relative to the
    largest impulse, after 3 steps at 1e-7. f64: 8.2e-4 measured, bound 3e-3. f32: 5.1e-3
    and 5.2e-3 measured (session 40; 1e-7 is close to f32's rounding of the impulse sums,
    2^-24 = 6e-8, so where each path stops is partly rounding), bound 2e-2. A wrong visiting
    order or a lost update is of order 1."""
    return 3e-3 if precision == "f64" else 2e-2


def test_bonded_cluster_under_a_moving_wall_matches_the_serial_schedule(precision):
    """A bonded pile carried sideways by its moving mould, converged tightly: the partitioned
    schedule (particle bond blocks split between the ranges and the boundary, NNCG) reaches
    the serial schedule's velocities and bond impulses. The two converge to each other with the
    tolerance (measured after 3 steps, largest difference over the largest value: velocities
    2.5e-5 / 5.3e-6 / 5.1e-7 and bond impulses 8.2e-4 / 1.4e-4 / 1.4e-5 at 1e-7 / 1e-8 / 1e-9;
    session 16, at 1e-7: 3.8e-5 and 8.7e-4). Run at 1e-7: 1e-8 took 85,000 sweeps per step,
    26 s of the suite; 1e-7 takes 7 s. The bounds are 3 to 5 times the measured differences,
    far below what a wrong visiting order or a lost update gives (order 1)."""
    (v_s, b_s), (v_p, b_p) = bonded_cluster([{"schedule": "serial"},
                                             {"schedule": "partitioned"}])
    assert np.abs(v_s).max() > 0.001 and np.abs(b_s).max() > 0
    assert np.abs(v_p - v_s).max() <= 2e-4 * np.abs(v_s).max()
    assert np.abs(b_p - b_s).max() <= bond_bound(precision) * np.abs(b_s).max()


def test_forward_and_symmetric_sweeps_reach_the_same_solution(precision):
    """The sweep order changes the path, not the solution: on the bonded pile above, forward
    sweeps and alternating forward-backward ones (serial schedule) end within the tolerance's
    reach of each other, with the bounds of the partitioned-schedule test; and they are not
    the same numbers (the setting acts)."""
    (v_f, b_f), (v_s, b_s) = bonded_cluster([{"schedule": "serial", "sweep_order": "forward"},
                                             {"schedule": "serial", "sweep_order": "symmetric"}])
    assert not np.array_equal(v_f, v_s)
    assert np.abs(v_f - v_s).max() <= 2e-4 * np.abs(v_s).max()
    assert np.abs(b_f - b_s).max() <= bond_bound(precision) * np.abs(b_s).max()


def test_a_batch_refuses_the_partitioned_schedule():
    a, _ = pour(n=20, steps=0, schedule="partitioned")
    b, _ = pour(n=20, steps=0, seed=4, schedule="partitioned")
    with pytest.raises(ValueError, match="partitioned schedule splits ONE system"):
        Simulation.batch([a, b])


def test_the_gpu_refuses_the_partitioned_schedule(monkeypatch):
    """Its workers wait for each other: safe on a CPU thread pool, not across GPU blocks."""
    from tcd import backend
    monkeypatch.setattr(backend, "arch", lambda: "gpu")
    with pytest.raises(ValueError, match="on the GPU use schedule"):
        Simulation([0.001], [[0, 0, 0.001]], settings=SolverSettings(schedule="partitioned"))


# --- session 43's mutation audit of the schedules, batching and the grid ------------------
def test_check_every_gives_the_serial_numbers_with_one_part():
    """check_every = 3: every step ends on a multiple of 3 sweeps (or max_sweeps), the pour
    still needs many sweeps (a test that measures a sweep that did not measure its sums
    would read 0 and stop at 3), and one part is the serial sweep bit for bit.
    Kills: nlgs_serial measuring on sweeps % check_every (off by one); close_sweep testing
    (sweeps + 1) % check_every."""
    a, sa = pour(steps=150, schedule="serial", check_every=3, max_sweeps=1000)
    b, sb = pour(steps=150, schedule="partitioned", threads=1, check_every=3, max_sweeps=1000)
    assert sa.max() > 20
    assert np.all((sa % 3 == 0) | (sa == 1000))
    assert np.array_equal(sa, sb)
    assert np.array_equal(a.positions(), b.positions())
    a.close()
    b.close()


def chain(order, threads=4):
    """Five spheres in a row along x, touching, the two ends thrown inwards, no gravity nor
    walls: with 4 parts the slabs are the spheres 0, 1, 2 and {3, 4}, so every interior list
    holds one contact at most and the boundary list the three others, which share bodies."""
    r = np.full(5, 0.005)
    x = np.zeros((5, 3))
    x[:, 0] = 2 * r * np.arange(5)
    v = np.zeros((5, 3))
    v[0, 0], v[4, 0] = 0.3, -0.2
    sim = Simulation(r, x, velocity=v,
                     settings=SolverSettings(schedule="partitioned", threads=threads,
                                             sweep_order=order, gravity=(0.0, 0.0, 0.0),
                                             tolerance=1e-13, max_sweeps=5000),
                     domain=((-0.01, -0.01, -0.01), (0.05, 0.01, 0.01)))
    rec = sim.step()
    cstart = sim.partition.cstart.to_numpy()[: threads + 2]
    out = (rec.sweeps, sim.velocities(), np.diff(cstart))
    sim.close()
    return out


def test_symmetric_order_reverses_the_boundary_list_too():
    """Interior lists of one contact read the same both ways, so forward and symmetric sweeps
    differ here only through the boundary list. Kills: the boundary list always swept
    forward."""
    sf, vf, sizes = chain("forward")
    ss, vs, _ = chain("symmetric")
    assert sizes[:-1].max() <= 1 and sizes[-1] >= 2, sizes
    assert sf > 4 and ss > 4
    assert not np.array_equal(vf, vs)


def bonded(blocks, steps=8, **settings):
    """test_partitioned's settled 60-grain pile (pile()), bonded, its mould moving sideways,
    then `steps` steps."""
    state, r = pile()
    wl = [walls.plane((0, 0, 0), (0, 0, 1)),
          walls.cylinder((0, 0, 0), (0, 0, 1), 0.0125, (0, 1), motion="constant",
                         velocity=(0.01, 0, 0))]
    sim = Simulation(r, state["particles/x"], walls=wl,
                     settings=SolverSettings(bond_blocks=blocks, **settings),
                     domain=((-0.05, -0.05, 0), (0.05, 0.05, 0.2)))
    sim.load_state_dict({**state, "walls/force": np.zeros((2, 3))})
    assert sim.create_bonds(gap_tolerance=5e-4) > 100
    sweeps = [sim.step().sweeps for _ in range(steps)]
    return sim, np.array(sweeps)


@pytest.mark.parametrize("blocks", [False, True])
def test_bond_item_lists_are_sound(blocks):
    """Every active bond item (a particle's bond block, or an intact bond) is listed once, an
    interior item's bodies all lie in its slab and a boundary item's do not; the same for the
    bonds' momentum lists. Kills: a block's
    crossing test reading bd.j (the partner only when the particle is bd.i)."""
    threads = 3
    sim, _ = bonded(blocks, steps=2, schedule="partitioned", threads=threads)
    pt, n = sim.partition, sim.n
    part = pt.part.to_numpy()[:n]
    d = sim.state_dict()
    bi, bj = d["bonds/i"], d["bonds/j"]
    intact = d["bonds/state"] == 0
    if blocks:
        bodies = [[q] + bj[(bi == q) & intact].tolist() + bi[(bj == q) & intact].tolist()
                  for q in range(n)]
    else:
        bodies = [[int(i), int(j)] if ok else [] for i, j, ok in zip(bi, bj, intact)]
    active = [q for q, b in enumerate(bodies) if len(b) > 1]
    bstart = pt.bstart.to_numpy()[: threads + 2]
    order = pt.border.to_numpy()[: bstart[-1]]
    assert sorted(order.tolist()) == active
    boundary = 0
    for k in range(threads + 1):
        for q in order[bstart[k]:bstart[k + 1]]:
            slabs = set(part[bodies[q]].tolist())
            if k < threads:
                assert slabs == {k}, (k, q, slabs)
            else:
                assert len(slabs) > 1, (q, slabs)
                boundary += 1
    assert boundary > 0 and bstart[threads] > 0
    # the bonds' momentum lists (every intact bond once; a bond of two slabs on the boundary
    # list, whose momentum one thread applies). Kills: bond_list checking only bd.i's slab.
    mstart = pt.mstart.to_numpy()[: threads + 2]
    morder = pt.morder.to_numpy()[: mstart[-1]]
    assert sorted(morder.tolist()) == np.nonzero(intact)[0].tolist()
    for k in range(threads + 1):
        slabs = part[bi[morder[mstart[k]:mstart[k + 1]]]], part[bj[morder[mstart[k]:mstart[k + 1]]]]
        if k < threads:
            assert np.all(slabs[0] == k) and np.all(slabs[1] == k), k
        else:
            assert mstart[k + 1] > mstart[k] and np.all(slabs[0] != slabs[1])
    sim.close()

