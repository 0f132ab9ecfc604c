"""Where the test suite's compile time goes: a pytest plugin that times the first call of each
kernel instance (Taichi compiles a kernel once per set of template arguments, i.e. per set of
fields, so the first call of an instance holds its compile time, or its load from Taichi's
offline cache, plus one run).

    PYTHONPATH=benchmarks PYTEST_ADDOPTS="-p compile_profile" COMPILE_PROFILE=/tmp/cp \\
        TI_OFFLINE_CACHE_FILE_PATH=$(mktemp -d) python -m pytest -q
    python benchmarks/compile_profile.py /tmp/cp

Each test process (the pytest-xdist workers, the f32 child, which PYTEST_ADDOPTS reaches too)
writes COMPILE_PROFILE.<pid>.kernels.txt (seconds, instances, kernel) and
COMPILE_PROFILE.<pid>.tests.txt (seconds, instances, test) when it ends; the second command
adds them up over the processes. An empty TI_OFFLINE_CACHE_FILE_PATH measures what a fresh
CI machine compiles. Processes that tests start themselves (`tcd run` children) are not
counted. Session 34 used it to cut the suite from 803 s to 485 s with an empty cache
(docs/testing.md).
"""
import atexit
import collections
import glob
import os
import sys
import time

import pytest

_kernels = collections.defaultdict(lambda: [0, 0.0])    # kernel name -> [instances, seconds]
_tests = {}


def _total():
    return (sum(v[1] for v in _kernels.values()), sum(v[0] for v in _kernels.values()))


def _install():
    import taichi.lang.kernel_impl as kernel_impl
    call = kernel_impl.Kernel.__call__

    def timed(self, *args, **kwargs):
        before = len(self.compiled_kernels)
        start = time.perf_counter()
        out = call(self, *args, **kwargs)
        if len(self.compiled_kernels) != before:     # a new instance: compiled (or loaded)
            entry = _kernels[self.func.__name__]
            entry[0] += 1
            entry[1] += time.perf_counter() - start
        return out
    kernel_impl.Kernel.__call__ = timed


def _write():
    prefix = os.environ.get("COMPILE_PROFILE", "compile_profile")
    pid = os.getpid()
    if not _kernels:
        return
    with open(f"{prefix}.{pid}.kernels.txt", "w") as f:
        for name, (count, seconds) in sorted(_kernels.items(), key=lambda kv: -kv[1][1]):
            f.write(f"{seconds:.3f} {count} {name}\n")
    with open(f"{prefix}.{pid}.tests.txt", "w") as f:
        for test, (seconds, count) in sorted(_tests.items(), key=lambda kv: -kv[1][0]):
            f.write(f"{seconds:.3f} {count} {test}\n")


def pytest_configure(config):
    _install()
    atexit.register(_write)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    seconds, count = _total()
    yield
    after = _total()
    _tests[item.nodeid] = (after[0] - seconds, after[1] - count)


def summarise(prefix: str, top: int = 25) -> str:
    """The per-kernel and per-test tables of all processes under `prefix`, added up."""
    kernels = collections.defaultdict(lambda: [0, 0.0])
    tests = collections.defaultdict(lambda: [0, 0.0])
    for kind, table in (("kernels", kernels), ("tests", tests)):
        for path in glob.glob(f"{prefix}.*.{kind}.txt"):
            with open(path) as f:
                for line in f:
                    seconds, count, name = line.split(maxsplit=2)
                    table[name.strip()][0] += int(count)
                    table[name.strip()][1] += float(seconds)
    if not kernels:
        raise SystemExit(f"no {prefix}.*.kernels.txt: run pytest with the plugin first")
    total = sum(v[1] for v in kernels.values())
    lines = [f"first calls: {total:.1f} s of CPU over {sum(v[0] for v in kernels.values())} "
             "kernel instances", "", "seconds  instances  kernel"]
    for name, (count, seconds) in sorted(kernels.items(), key=lambda kv: -kv[1][1])[:top]:
        lines.append(f"{seconds:8.1f}  {count:9d}  {name}")
    lines += ["", "seconds  instances  test"]
    for name, (count, seconds) in sorted(tests.items(), key=lambda kv: -kv[1][1])[:top]:
        lines.append(f"{seconds:8.1f}  {count:9d}  {name}")
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python benchmarks/compile_profile.py PREFIX (COMPILE_PROFILE of the run)")
    print(summarise(sys.argv[1]))
