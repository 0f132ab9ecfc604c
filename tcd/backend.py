"""One switch for Taichi backend and floating-point precision.

`init(arch, precision)` calls `ti.init` exactly once per process and fixes the real type used by
every field tcd allocates (`backend.real()`). Kernels use Taichi's `default_fp`, which `init`
sets to the same type, so no module spells `ti.f32` or `ti.f64` itself.
"""
from __future__ import annotations

import os

import taichi as ti

ARCHS = ("cpu", "gpu")
PRECISIONS = ("f64", "f32")

_state = {"arch": None, "precision": None, "serial_loops": False, "fast_math": True}

THREADS_ENV = "TCD_CPU_THREADS"   # the CPU thread pool's size when `init` is not given one
LOOPS_ENV = "TCD_PARALLEL_LOOPS"  # 0: the kernels' loops run inline (see serial_loops)
FAST_MATH_ENV = "TCD_FAST_MATH"   # 0: Taichi's fast math off (see init, loop_mode)


class BackendUnavailable(RuntimeError):
    """The backend asked for is not on this machine (arch='gpu' without a GPU)."""


OFFLINE_CACHE_BYTES = 1 << 30     # Taichi's compiled-kernel cache limit (see init)
CACHE_PATH_ENV = "TI_OFFLINE_CACHE_FILE_PATH"    # Taichi's own: where it caches kernels


def taichi_cache_path() -> str:
    """The folder Taichi 1.7 caches compiled kernels in, as Taichi finds it: a non-empty
    TI_OFFLINE_CACHE_FILE_PATH, else $XDG_CACHE_HOME/taichi/ticache where XDG_CACHE_HOME is
    set (empty too: /taichi/ticache), else ~/.cache/taichi/ticache."""
    given = os.environ.get(CACHE_PATH_ENV, "")
    if given:
        return given
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg is not None:
        return xdg.rstrip("/") + "/taichi/ticache"
    return os.path.join(os.path.expanduser("~"), ".cache", "taichi", "ticache")


def _cannot_write(folder: str) -> str | None:
    """Why this process cannot write files in `folder` (made if need be); None when it can."""
    import tempfile
    try:
        os.makedirs(folder, mode=0o700, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".tcd-probe-")
        os.close(fd)
        os.unlink(probe)
        return None
    except OSError as exc:
        return exc.strerror or str(exc)


def ensure_kernel_cache() -> None:
    """Make sure Taichi can write its kernel cache before ti.init: where it cannot (a HOME
    that is not a folder, a read-only one, TI_OFFLINE_CACHE_FILE_PATH under a file), Taichi
    1.7.4 ran the whole job and then died of a segmentation fault at exit, status 139
    (session 70's probe), offline cache on or off. Such a folder is replaced, with a note, by
    one of this user's own under the system's temporary folder (TI_OFFLINE_CACHE_FILE_PATH
    set to it, so that a `--jobs` worker uses it too); when that cannot be written either,
    ValueError says so before anything runs."""
    import tempfile
    wanted = taichi_cache_path()
    why = _cannot_write(wanted)
    if why is None:
        return
    uid = getattr(os, "getuid", lambda: "user")()
    fallback = os.path.join(tempfile.gettempdir(), f"tcd-taichi-cache-{uid}")
    other = _cannot_write(fallback)
    if other is None and hasattr(os, "getuid"):
        info = os.lstat(fallback)       # a folder of this user's own, not a link to another's
        if os.path.islink(fallback) or info.st_uid != os.getuid():
            other = "it is not a folder of this user's own"
    if other is not None:
        raise ValueError(f"Taichi's kernel cache {wanted} cannot be written ({why}), nor "
                         f"{fallback} ({other}): set {CACHE_PATH_ENV} to a folder that can")
    import sys
    print(f"tcd: note: Taichi's kernel cache {wanted} cannot be written ({why}): it caches "
          f"compiled kernels in {fallback} instead (set {CACHE_PATH_ENV} to choose)",
          file=sys.stderr)
    os.environ[CACHE_PATH_ENV] = fallback


def init(arch: str = "cpu", precision: str = "f64", *, debug: bool = False,
         cpu_threads: int | None = None, parallel_loops: bool | None = None,
         fast_math: bool | None = None) -> None:
    """Initialise Taichi for `arch` ("cpu" or "gpu") and `precision` ("f64" or "f32").
    `cpu_threads`: size of Taichi's CPU thread pool (default: the environment variable
    TCD_CPU_THREADS, else one per core). With one thread every kernel's parallel loops run
    inline on the launching thread (`serial_loops`). The kernels' parallel loops give the
    same numbers in any order and on any number of threads, but inline loops may differ from
    pooled ones in the last bits under fast math (`loop_mode`).
    `fast_math`: Taichi's fast math (default: the environment variable TCD_FAST_MATH, 0 or 1,
    else off on the CPU and on on a GPU). Off, the compiler keeps IEEE semantics and inline
    and pooled loops give the same numbers, so a run's numbers do not depend on `--jobs` or the
    thread settings (on by default until session 33; no speed cost measured on the CPU). On a
    GPU it stays on: there is no loop mode to agree with, and its cost there is unmeasured.
    `parallel_loops` (CPU only): whether the kernels' parallel loops go to the thread pool
    (default: the environment variable TCD_PARALLEL_LOOPS, 0 or 1, else yes unless the pool
    has one thread). When not, they run inline on the launching thread (`serial_loops`), all
    but the partitioned schedule's loop of workers, which is made for the pool.

    The environment variable TCD_KERNEL_PROFILER=1 turns on Taichi's kernel profiler
    (benchmarks/profile.py prints its table).

    A second call with the same arch and precision is a no-op (its thread and fast-math
    settings are ignored); one with another arch or precision raises, because Taichi cannot be
    re-initialised safely once fields exist.
    """
    if arch not in ARCHS:
        raise ValueError(f"unknown arch {arch!r}: expected one of {ARCHS}")
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}: expected one of {PRECISIONS}")
    if _state["arch"] is not None:
        if (_state["arch"], _state["precision"]) != (arch, precision):
            raise RuntimeError(
                f"tcd already initialised with arch={_state['arch']}, precision={_state['precision']};"
                f" cannot switch to arch={arch}, precision={precision} in the same process")
        return
    source = "cpu_threads"
    if cpu_threads is None and os.environ.get(THREADS_ENV, "").strip():
        cpu_threads, source = os.environ[THREADS_ENV].strip(), THREADS_ENV
    if cpu_threads is not None:
        raw = cpu_threads
        try:
            cpu_threads = int(raw)
        except (TypeError, ValueError):
            cpu_threads = 0
        if cpu_threads < 1 or (isinstance(raw, float) and raw != cpu_threads):
            raise ValueError(f"{source} must be a positive integer (threads of Taichi's CPU "
                             f"pool), got {raw!r}")
    if parallel_loops is None:
        parallel_loops = env_flag(LOOPS_ENV, cpu_threads != 1)
    if fast_math is None:
        fast_math = fast_math_setting(arch)
    if not isinstance(fast_math, bool):
        raise ValueError(f"fast_math must be True or False, got {fast_math!r}")
    from . import launch
    fast_launch = launch.enabled()          # a bad TCD_FAST_LAUNCH is refused before ti.init
    fp = ti.f64 if precision == "f64" else ti.f32
    ti_arch = ti.cpu if arch == "cpu" else gpu_arch()
    check_taichi_arch_env(arch)
    extra = {} if cpu_threads is None else {"cpu_max_num_threads": cpu_threads}
    if not os.environ.get("TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES"):
        # Taichi's offline kernel cache keeps 100 MB by default and evicts a quarter of it (least
        # recently used) when a process ends above that. tcd's kernels for a few capacity classes
        # in f64 and f32 exceed it (the test suite compiles about 96 MB), so runs evicted each
        # other's kernels and compiled them again (measured: tests/test_batch.py 119 s after
        # such evictions, 35 s with its kernels cached). TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES
        # (bytes) overrides this limit.
        extra["offline_cache_max_size_of_files"] = OFFLINE_CACHE_BYTES
    if os.environ.get("TCD_KERNEL_PROFILER", "") not in ("", "0"):
        extra["kernel_profiler"] = True     # benchmarks/profile.py: time per kernel
    ensure_kernel_cache()
    ti.init(arch=ti_arch, default_fp=fp, default_ip=ti.i32, debug=debug,
            offline_cache=True, log_level=ti.WARN, fast_math=fast_math, **extra)
    memoise_frontend()
    if fast_launch:
        launch.install()
    _state["arch"], _state["precision"] = arch, precision
    _state["fast_math"] = fast_math
    _state["serial_loops"] = arch == "cpu" and not parallel_loops


def fast_math_setting(arch: str) -> bool:
    """Whether Taichi's fast math is on: this process's setting once `init` has run, else what
    `init(arch)` without `fast_math` would choose: the environment variable TCD_FAST_MATH (0 or
    1), else off on the CPU and on on a GPU. A run records it in run.json, and a resumed run
    must match it."""
    if _state["arch"] is not None:
        return bool(_state["fast_math"])
    return env_flag(FAST_MATH_ENV, arch != "cpu")


def env_flag(name: str, default: bool) -> bool:
    """The environment variable `name` as a switch: 0 or 1, `default` when unset or blank;
    any other value is an error that names it."""
    value = os.environ.get(name, "").strip()
    if not value:
        return default
    if value not in ("0", "1"):
        raise ValueError(f"{name} must be 0 or 1, got {value!r}")
    return value == "1"


def loop_mode() -> str:
    """How this process runs the kernels' loops: "inline" or "pool" on the CPU (see
    `serial_loops`), else the arch. With Taichi's fast math the two CPU modes compile a loop's
    body differently (a serialised loop may be vectorised across its iterations), and the
    numbers differ in their last bits: the shear of a study sample by 2e-13 relative after two
    steps, and after a bond cascade visibly (seed 1 with rim rings: peak 0.8952 MPa at 2.50 mm
    inline, 0.8933 at 2.21 mm in the pool). A run's summary records it (`cpu_loops`); the same
    scenario, seed, backend and loop mode give the same numbers. `tcd run --jobs N` runs its
    workers inline when each has one core; TCD_PARALLEL_LOOPS=0 (or 1) chooses. With fast math
    off (the CPU's default since session 33; TCD_FAST_MATH=1 turns it on) the two modes agree
    (seed 1's first 12 shear steps, bit for bit), and the mode reads "inline (fast math off)" or
    "pool (fast math off)"."""
    if _state["arch"] != "cpu":
        mode = str(_state["arch"])
    else:
        mode = "inline" if _state["serial_loops"] else "pool"
    return mode if _state.get("fast_math", True) else mode + " (fast math off)"


def serial_loops() -> bool:
    """Whether the kernels' parallel loops run inline (read by every kernel when it compiles).

    True on the CPU backend with `init(parallel_loops=False)` (TCD_PARALLEL_LOOPS=0), and by
    default with a thread pool of one thread (`init(cpu_threads=1)`, TCD_CPU_THREADS=1).
    Taichi's CPU runtime hands every parallel loop to its thread pool and waits for it, a pool
    of one thread included: measured on this project's 2-core virtual machine, 160 us per loop
    against 20 us for the same loop inline, which made a time step of a two-sphere system cost
    4 ms (1 ms inline), and the serial shear of the 5857-sphere sample 1.47e-5 s per
    particle-step against 1.29e-5 inline. The partitioned schedule's loop of workers is never
    inline: it is the loop made for the pool."""
    return _state["serial_loops"]


def memoise_frontend() -> bool:
    """Memoise two pure functions of Taichi 1.7.4's Python frontend, which runs for every kernel
    instantiation of every process, offline cache or not (the cache skips only the compilation
    of the frontend's IR):

    - `ASTTransformerContext.get_pos_info(node)`: the source excerpt of an AST node, with a
      caret line under it, attached to every statement as debug information. It renders every
      excerpt with `textwrap` again for each instantiation of each kernel: 18 of the 74 s of a
      profiled tests/test_batch.py test (541 instantiations of about 100 kernels, since every
      new field container passed as a template is a new instantiation). The memo returns the
      very string Taichi renders, keyed by everything it reads (file, line offset, function
      name, indentation, the node's kind and span, the first line of its body, the source lines
      of the span), so the IR, the offline cache's keys and the error messages are unchanged.
    - `getsourcelines(func)` as the frontend calls it (`taichi.lang.kernel_impl`): a function's
      source, read and tokenised again for each instantiation; keyed by the function object.

    Installed once, by `init`; a Taichi without these functions is left alone. Returns whether
    the memo is in place."""
    try:
        from taichi.lang import kernel_impl
        from taichi.lang.ast import ast_transformer_utils as utils
        context = utils.ASTTransformerContext
        pos_info = context.get_pos_info
        sourcelines = kernel_impl.getsourcelines
    except (ImportError, AttributeError):
        return False
    if getattr(pos_info, "_tcd_memo", False):
        return True
    rendered: dict = {}

    def get_pos_info(self, node):
        try:
            body = getattr(node, "body", None)
            first = body[0].lineno if isinstance(body, list) and body else None
            last = max(node.end_lineno, node.lineno)
            key = (self.file, self.lineno_offset, self.func.func.__name__, self.indent,
                   type(node).__name__, node.lineno, node.end_lineno, node.col_offset,
                   node.end_col_offset, first, tuple(self.src[node.lineno - 1:last]))
        except (AttributeError, TypeError, IndexError):
            return pos_info(self, node)
        msg = rendered.get(key)
        if msg is None:
            msg = rendered[key] = pos_info(self, node)
        return msg

    sources: dict = {}

    def getsourcelines(func):
        try:
            lines, start = sources[func]
        except (KeyError, TypeError):
            lines, start = sourcelines(func)
            try:
                sources[func] = (tuple(lines), start)
            except TypeError:
                pass
            return lines, start
        return list(lines), start

    get_pos_info._tcd_memo = True
    get_pos_info.__wrapped__ = pos_info
    context.get_pos_info = get_pos_info
    kernel_impl.getsourcelines = getsourcelines
    return True


# GPU backends tried, in order, for arch="gpu". Not OpenGL: Taichi 1.7.4's probe of it
# crashes the process (segmentation fault) on a machine without a display or GPU, which is
# what `ti.init(arch=ti.gpu)` does when no CUDA, Metal or Vulkan device is found; and OpenGL
# has no f64.
GPU_ARCHS = ("cuda", "vulkan", "metal", "amdgpu")


def gpu_arch():
    """The first GPU backend of GPU_ARCHS that Taichi finds on this machine; BackendUnavailable
    naming those tried when there is none (instead of Taichi's silent fall back to the CPU,
    or its crash while probing OpenGL)."""
    from taichi.lang.misc import is_arch_supported
    for name in GPU_ARCHS:
        a = getattr(ti, name)
        if is_arch_supported(a):
            return a
    raise BackendUnavailable("arch 'gpu' requested but Taichi found no GPU backend on this machine "
                       f"(tried {', '.join(GPU_ARCHS)}); use arch='cpu'")


def check_available(arch: str) -> None:
    """Raise BackendUnavailable now if `arch` cannot run here, and ValueError if Taichi's own
    TI_ARCH would put it elsewhere (a run checks this before it writes anything). Does not
    initialise Taichi."""
    if _state["arch"] is None:
        check_taichi_arch_env(arch)
    if arch == "gpu" and _state["arch"] != "gpu":
        gpu_arch()


def check_taichi_arch_env(arch: str) -> None:
    """ti.init takes the environment's TI_ARCH over the arch it is given (with a note at
    Taichi's info level, which tcd does not show), and aborts the process on a name it does
    not know (TI_ARCH=cpu): a run asked for on the CPU went to a GPU, or died (session 74's
    review). Refused here by name, unless TI_ARCH names this CPU for arch "cpu" or one of
    GPU_ARCHS for arch "gpu" (a choice among the GPU backends: Taichi takes it)."""
    name = os.environ.get("TI_ARCH")
    if name is None:
        return
    known = ti._lib.core.Arch.__members__
    if name not in known:
        raise ValueError(f"the environment variable TI_ARCH={name!r} is not an arch Taichi "
                         f"knows ({', '.join(known)}), and Taichi would abort on it: unset TI_ARCH "
                         f"(tcd's arch is chosen with --arch, or tcd.init)")
    if (name in GPU_ARCHS) if arch == "gpu" else (known[name] == ti.cpu):
        return
    raise ValueError(f"the environment variable TI_ARCH={name!r} would make Taichi run on "
                     f"{name}, not on the arch asked for ({arch}): unset TI_ARCH (tcd's arch "
                     f"is chosen with --arch, or tcd.init)")


def initialized() -> bool:
    return _state["arch"] is not None


def arch() -> str:
    _require()
    return _state["arch"]


def precision() -> str:
    _require()
    return _state["precision"]


def real():
    """The Taichi real type chosen by `init` (ti.f64 or ti.f32)."""
    _require()
    return ti.f64 if _state["precision"] == "f64" else ti.f32


def numpy_real():
    import numpy as np
    _require()
    return np.float64 if _state["precision"] == "f64" else np.float32


def _require() -> None:
    if _state["arch"] is None:
        raise RuntimeError("call tcd.init(arch, precision) before using the engine")
