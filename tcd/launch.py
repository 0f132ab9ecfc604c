"""A shorter host path for launching tcd's own kernels (Taichi 1.7.4).

Every call of a Taichi kernel runs, in Python, before the kernel itself: the template lookup
(each argument's key rebuilt: weak references to containers, field addresses), the check that
every field ever created is placed (a loop over all of them and over every matrix field's
members), and the argument setting (a nest of closures per call). Measured on this project's
2-core machine (session 66), a time step of four spheres on the serial schedule, six launches,
cost 917 us: about 150 us per launch, of which the C++ launch is 9. A test suite makes hundreds
of thousands of such launches (tests/test_engine.py alone 248704), and the GPU's coloured
schedule makes one per colour and sweep.

`install()` (called once by `tcd.init`) replaces `Kernel.__call__` with one that, for kernels
defined in tcd's modules, remembers per kernel what the first call with a given set of template
arguments resolved to (Taichi's own instance, compiled and launched by Taichi's own path) and
launches it directly on the next calls with the same template arguments: the scalar arguments
set as Taichi sets them, Taichi's compiled kernel launched, its return values read as Taichi
reads them. The kernel, its IR and its numbers are Taichi's own; only the host's bookkeeping is
skipped. Taichi's full path still runs:

- on the first call of each set of template arguments (which compiles), and for any kernel not
  defined in tcd (Taichi's own field copies, user code);
- whenever a template argument is not the very object it was (containers are matched by
  identity, through weak references, so a freed container's reused id is never mistaken for
  it); for keyword arguments, a wrong number of arguments, or a scalar argument of another
  type (Taichi's path then raises its own error);
- with Taichi's autodiff (a tape or forward mode active);
- whenever a field was created or placed since the last launch (Taichi's materialisation and
  its checks run then, as they would).

TCD_FAST_LAUNCH=0 leaves Taichi's path for every call (tests/test_launch.py runs the same
steps both ways and compares every number bit for bit).
"""
from __future__ import annotations

import weakref

import numpy as np

FAST_LAUNCH_ENV = "TCD_FAST_LAUNCH"
MAX_ENTRIES = 4096          # template sets remembered per kernel (then Taichi's path only)
_state = {"installed": False, "launches": 0, "full": 0, "bypass": False}


def enabled() -> bool:
    """TCD_FAST_LAUNCH: 1 (the default) or 0; any other value is an error that names it."""
    from .backend import env_flag
    return env_flag(FAST_LAUNCH_ENV, True)


def counts() -> dict:
    """Launches through the short path and calls through Taichi's full path, since install."""
    return {"fast": _state["launches"], "full": _state["full"]}


class taichi_path:
    """`with launch.taichi_path():` every kernel call inside goes through Taichi's full path
    (the tests compare the two)."""

    def __enter__(self):
        self._was = _state["bypass"]
        _state["bypass"] = True
        return self

    def __exit__(self, *exc):
        _state["bypass"] = self._was
        return False


def installed() -> bool:
    return _state["installed"]


def install() -> bool:
    """Install the short path (once; a Taichi without the pieces it uses is left alone).
    `tcd.init` calls it unless TCD_FAST_LAUNCH=0. Returns whether it is in place."""
    if _state["installed"]:
        return True
    try:
        from taichi.lang import kernel_impl, shell
        Kernel = kernel_impl.Kernel
        impl, runtime_ops, ti_core = kernel_impl.impl, kernel_impl.runtime_ops, kernel_impl._ti_core
        cook_dtype, is_signed = kernel_impl.cook_dtype, kernel_impl.is_signed
        primitive_types, template = kernel_impl.primitive_types, kernel_impl.template
        handle_exception_from_cpp = kernel_impl.handle_exception_from_cpp
        no_autodiff = kernel_impl.AutodiffMode.NONE
        full_call = Kernel.__call__
        import taichi
        if tuple(taichi.__version__) != (1, 7, 4):      # the internals read here are 1.7.4's
            return False
    except (ImportError, AttributeError):
        return False
    real_ids = primitive_types.real_type_ids
    integer_ids = primitive_types.integer_type_ids
    pybuf = shell.pybuf_enabled
    immutable = (int, float, bool, str, type(None))
    composite = (tuple, list, dict, set)

    def plan_of(kernel):
        """Per argument: 't' template, 'f' real, 'i' signed, 'u' unsigned integer; None when
        the kernel is not tcd's or takes anything else."""
        module = getattr(kernel.func, "__module__", "") or ""
        if not module.startswith("tcd.") or kernel.autodiff_mode != no_autodiff:
            return None
        plan = []
        for arg in kernel.arguments:
            anno = arg.annotation
            if isinstance(anno, template):
                plan.append("t")
            elif id(anno) in real_ids:
                plan.append("f")
            elif id(anno) in integer_ids:
                plan.append("i" if is_signed(cook_dtype(anno)) else "u")
            else:
                return None
        if len([p for p in plan if p != "t"]) >= 64:
            return None
        ret = kernel.return_type
        if ret is not None:
            for r in ret:
                if not (id(r) in real_ids or id(r) in integer_ids):
                    return None
        return tuple(plan)

    def nothing_to_materialise(runtime) -> bool:
        """Whether Taichi's `runtime.materialize()` would do nothing: no field created or placed
        since it last ran (it empties these lists), no FieldsBuilder left unfinalised."""
        root_fb = impl._root_fb
        if (not runtime.materialized or not (root_fb.finalized or root_fb.empty)
                or runtime.global_vars or runtime.matrix_fields or runtime.grad_vars
                or runtime.dual_vars):
            return False
        return all(builder is root_fb for builder in runtime.unfinalized_fields_builder)

    def call(self, *args, **kwargs):
        fast = self.__dict__.get("_tcd_fast", 0)
        if fast == 0:
            plan = plan_of(self)
            fast = self._tcd_fast = None if plan is None else (plan, {})
        runtime = self.runtime
        if (fast is None or _state["bypass"] or kwargs or len(args) != len(fast[0])
                or runtime.fwd_mode_manager or runtime.target_tape):
            _state["full"] += 1
            return full_call(self, *args, **kwargs)
        plan, entries = fast
        templates = [a for p, a in zip(plan, args) if p == "t"]
        key = []
        for a in templates:
            if isinstance(a, immutable):
                key.append((type(a), a))
            elif isinstance(a, composite):          # rebuilt per call: Taichi's path
                _state["full"] += 1
                return full_call(self, *args)
            else:
                key.append(id(a))
        key = tuple(key)
        entry = entries.get(key)
        if entry is not None and (
                any(ref is not None and ref() is not a for ref, a in zip(entry[0], templates))
                # Taichi dropped its compiled kernel (SNodeTree.destroy clears compiled_kernels,
                # ti.reset and a new ti.init give the kernel a new dict) or its Program went
                # away: launching the entry would run freed code on freed fields
                or self.compiled_kernels.get(entry[4]) is not entry[1]
                or runtime.prog is not entry[3]):
            entry = None
        if entry is None or not nothing_to_materialise(runtime):
            _state["full"] += 1
            out = full_call(self, *args)
            instance, _ = self.mapper.lookup(args)
            ckey = (self.func, instance, self.autodiff_mode)
            kernel_cpp = self.compiled_kernels[ckey]
            refs = tuple(None if isinstance(a, immutable) else _ref(a) for a in templates)
            prog = impl.get_runtime().prog
            data = prog.compile_kernel(prog.config(), prog.get_device_caps(), kernel_cpp)
            if key in entries or len(entries) < MAX_ENTRIES:     # (a stale entry replaced)
                entries[key] = (refs, kernel_cpp, data, prog, ckey)
            return out
        _, kernel_cpp, data, prog, _ = entry
        ctx = kernel_cpp.make_launch_context()
        slot = 0
        for p, a in zip(plan, args):
            if p == "t":
                continue
            if p == "f":
                if not isinstance(a, (float, int, np.floating, np.integer)):
                    _state["full"] += 1
                    return full_call(self, *args)
                ctx.set_arg_float((slot,), float(a))
            else:
                if not isinstance(a, (int, np.integer)):
                    _state["full"] += 1
                    return full_call(self, *args)
                if p == "i":
                    ctx.set_arg_int((slot,), int(a))
                else:
                    ctx.set_arg_uint((slot,), int(a))
            slot += 1
        _state["launches"] += 1
        try:
            prog.launch_kernel(data, ctx)
        except Exception as e:     # as Taichi's own path reports it
            raise handle_exception_from_cpp(e) from None
        ret = None
        ret_dt = self.return_type
        if ret_dt is not None or self.has_print:
            runtime_ops.sync()
        if ret_dt is not None:
            ret = [self.construct_kernel_ret(ctx, r, (i,)) for i, r in enumerate(ret_dt)]
            if len(ret_dt) == 1:
                ret = ret[0]
        if pybuf:
            print(ti_core.pop_python_print_buffer(), end="")
        return ret

    call.__wrapped__ = full_call
    Kernel.__call__ = call
    _state["installed"] = True
    return True


def _ref(obj):
    """A weak reference where the object takes one (containers, fields), else a strong one
    wrapped to answer the same call."""
    try:
        return weakref.ref(obj)
    except TypeError:
        return lambda: obj

