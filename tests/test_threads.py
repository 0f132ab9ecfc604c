"""The kernels' loops give the same numbers handed to Taichi's thread pool or run inline
(tcd.backend.serial_loops) when Taichi's fast math is off (the CPU's default since session
33), and with Taichi's own IR optimisations on or off (TI_ADVANCED_OPTIMIZATION, off in the
tests for compile time): each side is a child process, and every number must match bit for
bit. With fast math on (TCD_FAST_MATH=1, the default until session 33) the two may differ in
the last bits, by host: a serialised loop may be vectorised across its iterations (session 32:
this test's bonded case passed on session 31's host and fails on session 32's, at the same
commit).

Also the settings of the thread pool and of the loops (TCD_CPU_THREADS, TCD_PARALLEL_LOOPS)
are checked before Taichi starts."""
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from conftest import ADVANCED_OPTIMIZATION_ENV, env_without_thread_settings

ROOT = pathlib.Path(__file__).resolve().parents[1]


def run_case():
    """A pour of 150 grains, 300 steps (serial and coloured schedules; the coloured one capped
    at 100 sweeps, as each of its colours is a parallel loop), then the serial one bonded and
    sheared by its moving mould: sweeps, positions, velocities, contact and bond impulses."""
    import dataclasses
    from test_partitioned import pour
    out = {}
    for name, settings in (("serial", {"schedule": "serial"}),
                           ("coloured", {"schedule": "coloured", "colouring": "greedy",
                                        "max_sweeps": 100})):
        sim, sweeps = pour(steps=300, **settings)
        out[name] = {"sweeps": sweeps.tolist(), "x": sim.positions().tolist(),
                     "v": sim.velocities().tolist(),
                     "impulse": sim.contact_arrays()["impulse"].tolist()}
        if name == "serial":
            assert sim.create_bonds(2e-4) > 20
            sim.set_walls([sim.walls[0], dataclasses.replace(
                sim.walls[1], motion="constant", velocity=(0.02, 0.0, 0.0), start=sim.time)])
            bonded = [sim.step().sweeps for _ in range(15)]
            d = sim.state_dict()
            out["bonded"] = {"sweeps": bonded, "x": sim.positions().tolist(),
                             "bonds": d["bonds/impulse"].tolist(),
                             "wall": sim.wall_force(1).tolist()}
        sim.close()
    return out


def side(backend, init: str, env: dict | None = None) -> dict:
    """run_case in a child process initialised with `init` (keywords of tcd.init), with the
    environment variables `env` set."""
    import json
    import textwrap
    arch, precision = backend
    code = textwrap.dedent(f"""
        import json, sys
        sys.path.insert(0, {str(ROOT)!r})
        sys.path.insert(0, {str(ROOT / "tests")!r})
        import tcd
        tcd.init({arch!r}, {precision!r}, {init})
        import taichi as ti
        from test_threads import run_case
        out = run_case()
        out["advanced_optimization"] = ti.lang.impl.current_cfg().advanced_optimization
        out["open_skip"] = tcd.solver.OPEN_SKIP
        print(json.dumps(out))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=900,
                         env=env_without_thread_settings(PYTHONPATH=str(ROOT), **(env or {})))
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def inline_side(backend):
    """run_case in a child with its loops inline (the CPU only), shared by the tests below."""
    if backend[0] != "cpu":
        pytest.skip("inline loops are a CPU setting")
    return side(backend, "cpu_threads=1")


def assert_same_numbers(a: dict, b: dict) -> None:
    assert set(a) == set(b)
    for case in a:
        for key in a[case]:
            assert np.array_equal(np.array(a[case][key]), np.array(b[case][key])), (case, key)


def test_loops_in_the_pool_or_inline_give_the_same_numbers(backend, inline_side):
    """With the CPU's default (fast math off since session 33) a run's numbers do not depend on
    whether its loops run inline (`tcd run --jobs N`, one core per worker) or in the pool (a
    single run on several cores). With fast math on they differed in their last bits, and a bond
    cascade made that a 4 % change in one sample's peak (docs/results.md, "Loop mode")."""
    # the pool's side also with Taichi's IR optimisations on, as a run outside the tests has
    # them (conftest.py turns them off for compile time): the same numbers either way
    inline = dict(inline_side)
    pool = side(backend, "cpu_threads=2, parallel_loops=True", {ADVANCED_OPTIMIZATION_ENV: "1"})
    assert max(inline["serial"]["sweeps"]) > 20          # impacts: many sweeps per step
    assert pool.pop("advanced_optimization") is True
    assert inline.pop("advanced_optimization") is (os.environ.get(ADVANCED_OPTIMIZATION_ENV) != "0")
    assert pool.pop("open_skip") == inline.pop("open_skip")
    assert_same_numbers(pool, inline)


def test_open_contact_early_return_changes_no_number(backend, inline_side):
    """A visit to a contact with no impulse that its law keeps open returns early (solver.
    OPEN_SKIP); without the early return (TCD_OPEN_SKIP=0) the serial, coloured and bonded
    cases of run_case give the same numbers bit for bit (a zero impulse may differ in its
    sign only, which array_equal does not see)."""
    full = side(backend, "cpu_threads=1", {"TCD_OPEN_SKIP": "0"})
    skip = dict(inline_side)
    for out in (full, skip):
        out.pop("advanced_optimization")
    assert full.pop("open_skip") is False
    if not skip.pop("open_skip"):
        pytest.skip("TCD_OPEN_SKIP=0 is set for the whole run")
    for case in ("serial", "coloured"):
        impulse = np.array(skip[case]["impulse"])
        # the early return is taken: open contacts with no impulse at the end of the run
        assert 0 < np.count_nonzero(np.all(impulse == 0.0, axis=1)) < len(impulse)
    assert_same_numbers(full, skip)


def test_open_skip_setting_is_checked():
    call = "from tcd import solver; print(solver.OPEN_SKIP)"
    # the default whatever the caller set for the whole run
    assert run_init({"TCD_OPEN_SKIP": None}, call).stdout.strip().splitlines()[-2] == "True"
    assert run_init({"TCD_OPEN_SKIP": "0"}, call).stdout.strip().splitlines()[-2] == "False"
    out = run_init({"TCD_OPEN_SKIP": "yes"}, call)
    assert out.returncode != 0 and "TCD_OPEN_SKIP must be 0 or 1, got 'yes'" in out.stderr


def run_init(env_extra, call="tcd.init('cpu', 'f64')"):
    env = env_without_thread_settings(**env_extra, PYTHONPATH=str(ROOT))
    env = {k: v for k, v in env.items() if v is not None}       # None: unset
    code = f"import tcd\nfrom tcd import backend\n{call}\nprint(backend.serial_loops())"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, env=env)


def test_thread_and_loop_settings_are_read_and_checked():
    assert run_init({"TCD_CPU_THREADS": "1"}).stdout.strip().endswith("True")
    assert run_init({"TCD_CPU_THREADS": "2"}).stdout.strip().endswith("False")
    both = {"TCD_CPU_THREADS": "1", "TCD_PARALLEL_LOOPS": "1"}
    assert run_init(both).stdout.strip().endswith("False")
    assert run_init({"TCD_PARALLEL_LOOPS": "0"}).stdout.strip().endswith("True")
    assert run_init({}, "tcd.init('cpu', 'f64', cpu_threads=1)").stdout.strip().endswith("True")
    for env, message in (({"TCD_CPU_THREADS": "two"}, "TCD_CPU_THREADS must be a positive integer"),
                         ({"TCD_CPU_THREADS": "0"}, "TCD_CPU_THREADS must be a positive integer"),
                         ({"TCD_PARALLEL_LOOPS": "yes"}, "TCD_PARALLEL_LOOPS must be 0 or 1")):
        out = run_init(env)
        assert out.returncode != 0 and message in out.stderr, (env, out.stderr[-500:])
    out = run_init({}, "tcd.init('cpu', 'f64', cpu_threads=-3)")
    assert out.returncode != 0 and "cpu_threads must be a positive integer" in out.stderr


def test_fast_math_setting_is_read_checked_and_recorded():
    """Taichi's fast math is off on the CPU unless TCD_FAST_MATH=1 (inline and pooled loops then
    agree in every bit), and the loop mode a run records says which."""
    call = "tcd.init('cpu', 'f64', cpu_threads=1); print(backend.loop_mode())"
    assert run_init({}, call).stdout.strip().splitlines()[-2] == "inline (fast math off)"
    assert run_init({"TCD_FAST_MATH": "0"}, call).stdout.strip().splitlines()[-2] == \
        "inline (fast math off)"
    assert run_init({"TCD_FAST_MATH": "1"}, call).stdout.strip().splitlines()[-2] == "inline"
    pool = "tcd.init('cpu', 'f64', cpu_threads=2, fast_math=False); print(backend.loop_mode())"
    # the keyword wins over the environment
    assert run_init({"TCD_FAST_MATH": "1"}, pool).stdout.strip().splitlines()[-2] == \
        "pool (fast math off)"
    # before init: what init would choose; on a GPU fast math stays on
    choice = "print(backend.fast_math_setting('gpu'), backend.fast_math_setting('cpu'))"
    assert run_init({}, choice).stdout.strip().splitlines()[-2] == "True False"
    assert run_init({"TCD_FAST_MATH": "0"}, choice).stdout.strip().splitlines()[-2] == "False False"
    on = "tcd.init('cpu', 'f64', cpu_threads=2, fast_math=True); print(backend.loop_mode())"
    assert run_init({}, on).stdout.strip().splitlines()[-2] == "pool"
    out = run_init({"TCD_FAST_MATH": "no"})
    assert out.returncode != 0 and "TCD_FAST_MATH must be 0 or 1" in out.stderr
    out = run_init({}, "tcd.init('cpu', 'f64', fast_math=1)")
    assert out.returncode != 0 and "fast_math must be True or False" in out.stderr


SCAN = ("import numpy as np, taichi as ti\nfrom tcd import contacts\n"
        "count, start = ti.field(ti.i32, shape=8), ti.field(ti.i32, shape=9)\n"
        "count.from_numpy(np.arange(8, dtype=np.int32))\n"
        "print('total', contacts.exclusive_scan(count, start, 8))")


def test_a_kernel_cache_that_cannot_be_written_is_replaced_not_a_crash_at_exit(tmp_path):
    """A HOME Taichi cannot write its kernel cache under (here a file; a read-only home, a
    TI_OFFLINE_CACHE_FILE_PATH under a file alike) let a run do all its work and then die of a
    segmentation fault at exit, status 139 (session 70's probe). Now the cache goes to a
    folder of the user's own under the temporary folder, with a note that says so."""
    blocked = tmp_path / "a_file"
    blocked.write_text("not a folder")
    (tmp_path / "tmp").mkdir()
    fallback = tmp_path / "tmp" / f"tcd-taichi-cache-{os.getuid()}"
    # the caller's own TI_OFFLINE_CACHE_FILE_PATH (a suite run with its cache elsewhere)
    # would take precedence over the blocked HOME: unset for that case
    for env in ({"HOME": str(blocked / "home"), "TI_OFFLINE_CACHE_FILE_PATH": None},
                {"TI_OFFLINE_CACHE_FILE_PATH": str(blocked / "cache")}):
        env = dict(env, TMPDIR=str(tmp_path / "tmp"), XDG_CACHE_HOME=None)
        out = run_init(env, f"tcd.init('cpu', 'f64')\n{SCAN}")
        assert out.returncode == 0, (env, out.returncode, out.stderr[-800:])
        assert "total 28" in out.stdout, out.stdout
        assert (f"tcd: note: Taichi's kernel cache {blocked}/" in out.stderr
                and "cannot be written (Not a directory): it caches compiled kernels in "
                f"{fallback} instead" in out.stderr), out.stderr[-800:]
        assert any(fallback.iterdir())          # kernels cached there


def test_tcd_knows_where_taichi_caches_its_kernels(tmp_path):
    """backend.taichi_cache_path, which ensure_kernel_cache checks, is the folder Taichi itself
    chose: TI_OFFLINE_CACHE_FILE_PATH, else $XDG_CACHE_HOME/taichi/ticache, else
    ~/.cache/taichi/ticache."""
    call = ("tcd.init('cpu', 'f64')\nimport taichi as ti\n"
            "print('paths', ti.lang.impl.current_cfg().offline_cache_file_path, "
            "backend.taichi_cache_path())")
    unset = {"TI_OFFLINE_CACHE_FILE_PATH": None}        # the caller's, if set, would win
    for env in ({"XDG_CACHE_HOME": None, **unset}, {"XDG_CACHE_HOME": str(tmp_path / "xdg"), **unset},
                {"TI_OFFLINE_CACHE_FILE_PATH": str(tmp_path / "given")}):
        out = run_init(env, call)
        line = [t for t in out.stdout.splitlines() if t.startswith("paths ")]
        assert out.returncode == 0 and line, out.stderr[-500:]
        taichi_path, ours = line[0].split()[1:]
        assert os.path.abspath(taichi_path) == os.path.abspath(ours), env


def test_taichi_s_own_arch_variable_is_refused_unless_it_names_the_arch_asked_for(tmp_path):
    """ti.init takes TI_ARCH from the environment over the arch it is given, and aborts the
    process on a name it does not know: with TI_ARCH=cuda exported, a run asked for on the
    CPU would go to the GPU; with TI_ARCH=cpu it died of Taichi's assertion (session 74's
    review). Now both are refused by name, before `tcd run` writes anything; TI_ARCH naming
    this CPU is taken."""
    import platform
    host = "arm64" if platform.machine().lower() in ("arm64", "aarch64") else "x64"
    out = run_init({"TI_ARCH": host})
    assert out.returncode == 0, out.stderr[-800:]
    for name, message in (("cuda", "TI_ARCH='cuda' would make Taichi run on cuda, not on the "
                                   "arch asked for (cpu): unset TI_ARCH"),
                          ("cpu", "TI_ARCH='cpu' is not an arch Taichi knows (x64, ")):
        out = run_init({"TI_ARCH": name})
        assert out.returncode == 1 and message in out.stderr, (name, out.returncode, out.stderr[-800:])
        run = tmp_path / name
        cli = subprocess.run([sys.executable, "-m", "tcd.cli", "run", str(ROOT / "scenarios" / "tiny.toml"),
                              "--out", str(run)], capture_output=True, text=True, timeout=300,
                             env=env_without_thread_settings(PYTHONPATH=str(ROOT), TI_ARCH=name))
        assert cli.returncode != 0 and message in cli.stderr, (name, cli.returncode, cli.stderr[-800:])
        assert "Traceback" not in cli.stderr and not run.exists()


def test_a_process_without_home_runs(tmp_path):
    """Taichi 1.7.4 aborts at its import when HOME is unset (a cron job, a service, `env -i`):
    `import tcd` now sets it from the password database first (session 74's review)."""
    out = run_init({"HOME": None, "TI_OFFLINE_CACHE_FILE_PATH": str(tmp_path / "cache")},
                   f"tcd.init('cpu', 'f64')\n{SCAN}")
    assert out.returncode == 0, (out.returncode, out.stderr[-800:])
    assert "total 28" in out.stdout
