"""tcd.launch: the short host path for tcd's kernels launches Taichi's own compiled kernels with
the arguments Taichi would set, so every number is the same as through Taichi's full path; and
it falls back to that path whenever its memory could be stale (a new container, a new field, a
scalar of another type)."""
import os
import pathlib

import numpy as np
import pytest
import taichi as ti

from tcd import contacts, launch, packing, walls
from tcd.simulation import Simulation, SolverSettings

from conftest import schedule_settings

R = 0.012


def bonded_pour(schedule: str, n: int = 60):
    """A pour into a mould that starts to shake, then bonded and sheared by its mould: the
    record of every step (sweeps, residual, contacts), the final positions, velocities, spins
    and the walls' forces."""
    rng = np.random.default_rng(5)
    r = packing.course_radii("surface", n, rng) * 0.3
    x = packing.lattice_column(r, 2 * R, 0.0, rng, max_height=0.1)
    top = float(x[:, 2].max() + r.max())
    wl = [walls.plane((0, 0, 0), (0, 0, 1), radius=R, name="bottom"),
          walls.cylinder((0, 0, 0), (0, 0, 1), R, (0.0, top + 0.01), friction=0.2,
                         motion="sine", amplitude=(0, 0, 2e-4), frequency=30.0, name="mould")]
    sim = Simulation(r, x, walls=wl, friction=0.7, domain=((-R, -R, 0.0), (R, R, top)),
                     settings=SolverSettings(max_sweeps=200, **schedule_settings(schedule)))
    records = [sim.step() for _ in range(120)]
    assert sim.create_bonds(2e-4) > 10
    sim.set_walls([sim.walls[0], sim.walls[1].moving_from(sim.time, (0.02, 0.0, 0.0))])
    records += [sim.step() for _ in range(40)]
    out = {"records": [(r.sweeps, r.residual, r.contacts) for r in records],
           "x": sim.positions(), "v": sim.velocities(), "w": sim.angular_velocities(),
           "walls": [sim.wall_force(k) for k in range(2)], "bonds": sim.bonds_state_counts()}
    sim.close()
    return out


@pytest.fixture
def short_path():
    """The short path is on in this process (tcd.init installs it unless TCD_FAST_LAUNCH=0 was
    set for the whole run, as for a measurement of Taichi's own path)."""
    if not launch.enabled():
        pytest.skip("TCD_FAST_LAUNCH=0 is set for the whole run")
    assert launch.installed()


@pytest.mark.parametrize("schedule", ["serial", "coloured"])
def test_short_path_gives_taichis_numbers_bit_for_bit(schedule, short_path):
    before = launch.counts()
    fast = bonded_pour(schedule)
    after = launch.counts()
    # 160 steps of five launches on the serial schedule (more on the coloured one)
    assert after["fast"] - before["fast"] > 4 * 160, "the steps went through the short path"
    with launch.taichi_path():
        full = bonded_pour(schedule)
    assert launch.counts()["fast"] == after["fast"], "none through the short path inside taichi_path"
    again = bonded_pour(schedule)              # the same pooled containers, remembered launches
    assert launch.counts()["fast"] > after["fast"]
    assert max(s for s, _, _ in full["records"]) > 5, "the pour must reach the floor"
    for other in (full, again):
        assert other["records"] == fast["records"]
        for key in ("x", "v", "w"):
            np.testing.assert_array_equal(other[key], fast[key])
        for a, b in zip(other["walls"], fast["walls"]):
            np.testing.assert_array_equal(a, b)
        assert other["bonds"] == fast["bonds"]


def test_another_container_or_a_new_field_takes_taichis_path(backend, short_path):
    count = ti.field(ti.i32, shape=64)
    start = ti.field(ti.i32, shape=65)
    count.from_numpy(np.arange(64, dtype=np.int32))
    assert contacts.exclusive_scan(count, start, 64) == 63 * 64 // 2     # compiles: full path
    c0 = launch.counts()
    assert contacts.exclusive_scan(count, start, 64) == 63 * 64 // 2
    c1 = launch.counts()
    assert (c1["fast"] - c0["fast"], c1["full"] - c0["full"]) == (1, 0)
    # a field created since: Taichi's materialisation and its checks run (the full path) once
    other = ti.field(ti.i32, shape=64)
    c2 = launch.counts()
    assert contacts.exclusive_scan(count, start, 10) == 45
    c3 = launch.counts()
    assert (c3["fast"] - c2["fast"], c3["full"] - c2["full"]) == (0, 1)
    assert contacts.exclusive_scan(count, start, 10) == 45
    assert launch.counts()["fast"] - c3["fast"] == 1
    other.from_numpy(np.full(64, 2, dtype=np.int32))
    # another container of the same shape: its own instance, its own numbers
    assert contacts.exclusive_scan(other, start, 64) == 128
    assert contacts.exclusive_scan(count, start, 64) == 63 * 64 // 2
    assert contacts.exclusive_scan(other, start, 64) == 128
    np.testing.assert_array_equal(start.to_numpy()[:65], np.arange(65) * 2)


def test_a_scalar_of_the_wrong_type_gets_taichis_error(backend, short_path):
    count = ti.field(ti.i32, shape=8)
    start = ti.field(ti.i32, shape=9)
    assert contacts.exclusive_scan(count, start, 8) == 0
    assert contacts.exclusive_scan(count, start, 8) == 0      # remembered
    full = launch.counts()["full"]
    with pytest.raises(ti.TaichiRuntimeTypeError):
        contacts._exclusive_scan(count, start, 8.5, 64, contacts._scan_scratch["field"])
    assert launch.counts()["full"] == full + 1


def test_the_switch_is_0_or_1(monkeypatch):
    monkeypatch.setenv(launch.FAST_LAUNCH_ENV, "0")
    assert launch.enabled() is False
    monkeypatch.setenv(launch.FAST_LAUNCH_ENV, "yes")
    with pytest.raises(ValueError, match="TCD_FAST_LAUNCH must be 0 or 1"):
        launch.enabled()


RESET_SCRIPT = """
import sys
import taichi as ti
from tcd import launch
ti.init(arch=ti.cpu, offline_cache=False, log_level=ti.WARN)
assert launch.install()
def add(x: ti.i32) -> ti.i32:
    return x + a[None]
add.__module__ = "tcd.fake"         # a kernel of tcd's own, to the short path
add = ti.kernel(add)
a = ti.field(ti.i32, shape=())
a[None] = 100
first = [add(1), add(2)]
fast = launch.counts()["fast"]
ti.reset()
ti.init(arch=ti.cpu, offline_cache=False, log_level=ti.WARN)
a = ti.field(ti.i32, shape=())
a[None] = 7
print(first, fast, add(1), add(1), launch.counts()["fast"] - fast)
"""


def test_a_kernel_taichi_dropped_is_not_launched_again(tmp_path):
    """After ti.reset and a new ti.init (or a destroyed SNode tree) Taichi throws its compiled
    kernels away; the short path kept launching the old one, on the old program: a
    segmentation fault (session 69's review of the launch path)."""
    import subprocess
    import sys
    script = tmp_path / "reset.py"          # (a kernel's source must be in a file)
    script.write_text(RESET_SCRIPT)
    root = pathlib.Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         timeout=300, cwd=str(root), env={**os.environ, "PYTHONPATH": str(root),
                                                          launch.FAST_LAUNCH_ENV: "1"})
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert out.stdout.strip().splitlines()[-1] == "[101, 102] 1 8 8 1", out.stdout
