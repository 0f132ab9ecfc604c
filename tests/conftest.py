"""Session-wide Taichi initialisation: `ti.init` may run once per process.

`--precision f32` runs the physics tests in single precision; tests read their tolerances
from the `tol` fixture, which follows the precision.

Every test process (each pytest-xdist worker holds one core) and every process a test starts
runs Taichi's CPU kernels on one thread with their loops inline (TCD_CPU_THREADS=1, see
tcd.backend.serial_loops), unless TCD_CPU_THREADS or TCD_PARALLEL_LOOPS is set. With Taichi's
fast math on (TCD_FAST_MATH=1; off by default on the CPU since session 33) a loop body may
compile differently inline, and the numbers may differ in their last bits (backend.loop_mode);
with it off, the default, they agree (tests/test_threads.py, two child processes). A loop handed
to the pool costs about 160 us on this project's machine against 20 us inline.

Compile time: with an empty kernel cache, compiling was half of the suite's time. On the CPU
the tests run the coloured schedule one colour per solve call (TCD_COLOURS_PER_LAUNCH=1) and
Taichi without its own IR optimisations (TI_ADVANCED_OPTIMIZATION=0), unless those are set:
the same numbers as the defaults, a fraction of the compile time (see pytest_configure).
"""
import os
import pathlib
import signal

# Taichi, imported with pytest capturing stdout, sends every kernel's print buffer through
# Python after every launch (taichi/lang/shell.py; 2 % of a profiled tests/test_engine.py);
# tcd's kernels print nothing. Read when taichi is imported, so set before tcd is.
os.environ.setdefault("TI_ENABLE_PYBUF", "0")

import pytest  # noqa: E402

import tcd  # noqa: E402
from tcd.signals import STOP_SIGNALS  # noqa: E402  (stdlib only; imported here, not after a fork)

# read by ti.init (Taichi takes any of its settings from TI_<NAME>)
ADVANCED_OPTIMIZATION_ENV = "TI_ADVANCED_OPTIMIZATION"


def pytest_addoption(parser):
    parser.addoption("--arch", default="cpu", choices=("cpu", "gpu"))
    parser.addoption("--precision", default="f64", choices=("f64", "f32"))


@pytest.fixture(scope="session", autouse=True)
def backend(request):
    arch = request.config.getoption("--arch")
    precision = request.config.getoption("--precision")
    tcd.init(arch, precision)
    return arch, precision


@pytest.fixture(scope="session")
def on_backend(backend):
    """The session's backend as keyword arguments (arch=, precision=) of tcd.bench's runs."""
    return {"arch": backend[0], "precision": backend[1]}


@pytest.fixture(scope="session")
def precision(backend):
    return backend[1]


@pytest.fixture(scope="session")
def tol(precision):
    """Relative tolerance for quantities that are exact up to rounding."""
    return 1e-9 if precision == "f64" else 2e-4


@pytest.fixture(scope="session")
def benchmark_script():
    """load(name): the module benchmarks/<name>.py (scripts, not a package), imported by path."""
    import importlib.util
    import pathlib
    root = pathlib.Path(__file__).resolve().parents[1]

    def load(name):
        spec = importlib.util.spec_from_file_location(name, root / "benchmarks" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    return load


def schedule_settings(name: str) -> dict:
    """SolverSettings keywords of a schedule name of the parametrised tests: "serial",
    "partitioned", "coloured" (its colouring as on the backend), "coloured-greedy",
    "coloured-rounds" (the parallel colouring, the GPU's, run on the CPU too)."""
    if name.startswith("coloured-"):
        return {"schedule": "coloured", "colouring": name.split("-", 1)[1]}
    return {"schedule": name}


def assert_batch_steps_as_alone(sims, steps: int):
    """Step each simulation of `sims` alone and all of them batched, `steps` times: at every
    step the batch's sweeps per system must be each one's alone, and at the end its positions
    and velocities theirs, bit for bit. Returns the batch and the sweeps alone (steps x
    systems)."""
    import numpy as np
    from tcd.simulation import Simulation
    batch = Simulation.batch(list(sims))
    sweeps = []
    for _ in range(steps):
        sweeps.append([o.step().sweeps for o in sims])
        batch.step()
        np.testing.assert_array_equal(batch.system_stats()[0], sweeps[-1])
    x, v = batch.positions(), batch.velocities()
    for s, o in enumerate(sims):
        np.testing.assert_array_equal(x[batch.system_slice(s)], o.positions())
        np.testing.assert_array_equal(v[batch.system_slice(s)], o.velocities())
    return batch, np.array(sweeps)


def run_tcd(argv) -> int:
    """`tcd run` (cli.main) on the session's backend (the --arch and --precision tcd.init was
    given) where argv names none: the same runs in every configuration of the suite."""
    from tcd import backend, cli
    argv = list(argv)
    if "--arch" not in argv:
        argv += ["--arch", backend.arch()]
    if "--precision" not in argv:
        argv += ["--precision", backend.precision()]
    return cli.main(argv)


def default_stop_signals() -> None:
    """preexec_fn of a child whose answer to a stop signal a test checks: SIGINT, SIGTERM and
    SIGHUP at their default actions in it. A shell without job control starts a background
    command (`pytest ... &`) with SIGINT ignored, `nohup` starts it with SIGHUP ignored, and
    an ignored signal stays ignored through fork and exec; tcd keeps ignoring a signal it was
    started ignoring (signals.SignalScope), as `nohup` asks. Without this such a child ran to
    its end, as it should, and the test failed because of the shell the suite was started
    from (session 74: the closed terminal's test under `nohup`; session 72's Ctrl-C "lost"
    under load was a suite started in the background)."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_DFL)
    if hasattr(signal, "pthread_sigmask"):      # a blocked signal is inherited too
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


def env_without_thread_settings(**extra) -> dict:
    """This process's environment for a child, less TCD_CPU_THREADS, TCD_PARALLEL_LOOPS
    (pytest_configure sets the first) and TCD_FAST_MATH, plus `extra`."""
    from tcd import backend as tcd_backend
    env = {k: v for k, v in os.environ.items()
           if k not in (tcd_backend.THREADS_ENV, tcd_backend.LOOPS_ENV, tcd_backend.FAST_MATH_ENV)}
    env.update(extra)
    return env


@pytest.fixture
def small_classes(monkeypatch):
    """Capacity classes from 64 slots instead of tcd.state.MIN_SLOTS (1024), for the tests
    whose small simulations must outgrow their buffers or shrink them."""
    from tcd import state
    monkeypatch.setattr(state, "MIN_SLOTS", 64)


@pytest.fixture
def other_side(tmp_path, backend):
    """run(code): run `code` (Python, after `import tcd` and `tcd.init`, with tests/ on the
    path; its last printed line is JSON) in a child process on the other side of
    tcd.backend.serial_loops: a pool of two threads with parallel loops when this process runs
    inline, one thread inline otherwise. Returns the parsed JSON."""
    import json
    import pathlib
    import subprocess
    import sys
    import textwrap
    from tcd import backend as tcd_backend
    arch, precision = backend
    root = pathlib.Path(__file__).resolve().parents[1]
    inline_here = tcd_backend.serial_loops()
    init = "cpu_threads=2, parallel_loops=True" if inline_here else "cpu_threads=1"
    init += f", fast_math={tcd_backend.fast_math_setting(arch)}"     # this process's setting

    def run(code: str):
        script = tmp_path / "other_side.py"
        script.write_text(textwrap.dedent(f"""
            import json, sys
            sys.path.insert(0, {str(root)!r})
            sys.path.insert(0, {str(root / "tests")!r})
            import tcd
            from tcd import backend
            tcd.init({arch!r}, {precision!r}, {init})
            assert backend.serial_loops() is {not inline_here}
        """) + textwrap.dedent(code))
        env = env_without_thread_settings(PYTHONPATH=str(root))
        out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                             timeout=900, env=env)
        assert out.returncode == 0, out.stderr[-3000:]
        return json.loads(out.stdout.strip().splitlines()[-1])
    return run


@pytest.fixture
def schedule_on_backend(backend):
    """check(schedule): skip a test of the CPU-only partitioned schedule on the GPU."""
    def check(schedule):
        if schedule == "partitioned" and backend[0] != "cpu":
            pytest.skip("the partitioned schedule runs on the CPU")
    return check


# the longest files first: with `-n auto --dist loadfile` each file goes to the next free
# worker in collection order, so the f32 child run (about 3 min) and the twin (about 2 min)
# started last would leave one core idle at the end of the suite
_FIRST = ("test_precision_f32.py", "test_twin.py")


def pytest_configure(config):
    # the processes the tests start import this checkout's tcd too (pyproject's pythonpath
    # covers this process only)
    root = str(pathlib.Path(__file__).resolve().parents[1])
    paths = os.environ.get("PYTHONPATH", "")
    if root not in paths.split(os.pathsep):
        os.environ["PYTHONPATH"] = root + (os.pathsep + paths if paths else "")
    if not (os.environ.get("TCD_CPU_THREADS") or os.environ.get("TCD_PARALLEL_LOOPS")):
        os.environ["TCD_CPU_THREADS"] = "1"
    cpu = config.getoption("--arch") == "cpu"
    if cpu and not os.environ.get("TCD_COLOURS_PER_LAUNCH"):
        # the coloured schedule's solve kernel with one colour per call, not the default 4
        # unrolled: the same numbers (test_engine.py, test_colours_per_launch_changes_no_number,
        # runs the default too), and 0.9 s to compile on the CPU instead of 7.6 s, for each of
        # its instances (one per set of fields: 7 in test_bonds' oversized-colour-set test,
        # 92 s -> 42 s with an empty kernel cache)
        os.environ["TCD_COLOURS_PER_LAUNCH"] = "1"
    if cpu and not os.environ.get(ADVANCED_OPTIMIZATION_ENV):
        # Taichi's own IR optimisations off (LLVM's stay): the same numbers bit for bit
        # (test_threads.py runs a child with them on), 3.5 times less compile time for the
        # largest kernels (nlgs_serial 2.2 s -> 0.6 s, solve_colours 0.9 s -> 0.4 s), and
        # with an empty kernel cache compiling was half of the suite's time
        os.environ[ADVANCED_OPTIMIZATION_ENV] = "0"
    config.addinivalue_line(
        "markers", "f64_only: the test compares two runs of the same code (a buffer refit, a "
        "launch split, a neighbour skin) bit for bit, which does not depend on the precision, "
        "or runs a tool that works in f64 itself (the renderer's reference image), or checks "
        "integer bookkeeping no floating-point number enters (the scans, the colouring, the "
        "pool of containers): the f32 pass (test_precision_f32.py, --precision f32) skips it")


def pytest_collection_modifyitems(session, config, items):
    if config.getoption("--precision") == "f32":
        skip = pytest.mark.skip(reason="f64_only: does not depend on the precision, checked in f64")
        for item in items:
            if item.get_closest_marker("f64_only"):
                item.add_marker(skip)
    rank = {name: k for k, name in enumerate(_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(_FIRST)))   # stable: else unchanged


@pytest.fixture
def stub(monkeypatch):
    """stub("runner", run_scenario=f): `tcd.runner` is a fake module for this test (the
    command-line tests: no simulation runs)."""
    def install(name, **attrs):
        import sys
        import types
        module = types.ModuleType(f"tcd.{name}")
        module.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, f"tcd.{name}", module)
        monkeypatch.setattr(tcd, name, module, raising=False)
        return module
    return install


@pytest.fixture
def runner_calls(stub):
    """`tcd.runner.run_scenario` stubbed: each call's arguments recorded."""
    calls = []

    def run_scenario(scenario, out_dir, *, resume=False, progress=True, jobs=1):
        calls.append(dict(scenario=scenario, out_dir=out_dir, resume=resume, progress=progress, jobs=jobs))
        return {"scenario": scenario.name, "tau_peak_MPa": 0.8371234567}
    stub("runner", run_scenario=run_scenario)
    return calls
