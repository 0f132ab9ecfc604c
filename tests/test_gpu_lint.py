"""Static checks of the kernels for patterns that break on the GPU backend only (CI has no
GPU, so these are read off the source).

Taichi 1.7.4 hands values set before a kernel's parallel loop to that loop through global
temporaries; a vector of f64 there is misaligned on CUDA and every launch dies with
CUDA_ERROR_MISALIGNED_ADDRESS (seen on an H100: solver.predict built its gravity vector that
way, and every f64 GPU step crashed). Scalars are aligned by Taichi and are fine.
"""
import ast
import pathlib

import tcd

SOURCES = sorted(pathlib.Path(tcd.__file__).parent.glob("*.py"))
VECTOR_MAKERS = {"Vector", "Matrix", "vec2", "vec3", "vec4", "zero"}


def _is_kernel(node):
    return isinstance(node, ast.FunctionDef) and any(
        isinstance(d, ast.Attribute) and d.attr == "kernel" for d in node.decorator_list)


def _makes_vector(value):
    return any(isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
               and n.func.attr in VECTOR_MAKERS for n in ast.walk(value))


def _is_func(node):
    return isinstance(node, ast.FunctionDef) and any(
        isinstance(d, ast.Attribute) and d.attr == "func" for d in node.decorator_list)


def _static_if(st):
    """`if ti.static(...):` (resolved when compiling: its body stays at the same level)."""
    return (isinstance(st, ast.If) and isinstance(st.test, ast.Call)
            and isinstance(st.test.func, ast.Attribute) and st.test.func.attr == "static")


def _top_level(body, funcs, seen=()):
    """A kernel's top-level statements as Taichi compiles them: the bodies of `if ti.static`
    and of the ti.funcs called at the top level (solver.step_begin's and step_end's step
    kernels, `contacts._contact_pass`, ...) inlined where they are called."""
    out = []
    for st in body:
        if _static_if(st):
            out += _top_level(st.body + st.orelse, funcs, seen)
        elif isinstance(st, ast.Expr) and isinstance(st.value, ast.Call):
            f = st.value.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)
            if name in funcs and name not in seen:
                out += _top_level(funcs[name].body, funcs, seen + (name,))
            else:
                out.append(st)
        else:
            out.append(st)
    return out


def vectors_handed_to_loops(source: str, funcs: dict | None = None):
    """(kernel, name, line) for each vector set at a kernel's top level and used by a later
    top-level loop. `funcs`: ti.funcs by name (those of `source` by default), inlined where a
    kernel calls them at its top level."""
    tree = ast.parse(source)
    if funcs is None:
        funcs = {n.name: n for n in ast.walk(tree) if _is_func(n)}
    found = []
    for node in ast.walk(tree):
        if not _is_kernel(node):
            continue
        vectors = {}
        for st in _top_level(node.body, funcs):
            if isinstance(st, (ast.For, ast.While)):
                used = {n.id for n in ast.walk(st) if isinstance(n, ast.Name)}
                found += [(node.name, name, line) for name, line in vectors.items() if name in used]
            elif isinstance(st, ast.Assign) and _makes_vector(st.value):
                for t in st.targets:
                    for n in ast.walk(t):
                        if isinstance(n, ast.Name):
                            vectors[n.id] = st.lineno
    return found


def test_the_check_finds_the_pattern():
    bad = ("@ti.kernel\ndef k(p: ti.template(), gx: float):\n    g = ti.Vector([gx, 0.0, 0.0])\n"
           "    for i in range(4):\n        p.v[i] += g\n")
    good = ("@ti.kernel\ndef k(p: ti.template(), gx: float):\n    for i in range(4):\n"
            "        g = ti.Vector([gx, 0.0, 0.0])\n        p.v[i] += g\n")
    assert vectors_handed_to_loops(bad) == [("k", "g", 3)]
    assert vectors_handed_to_loops(good) == []
    # the same in a ti.func called at a kernel's top level (inside a static if), and not in
    # one called inside its loop
    func = ("@ti.func\ndef body(p: ti.template(), gx: ti.template()):\n"
            "    g = ti.Vector([gx, 0.0, 0.0])\n    for i in range(4):\n        p.v[i] += g\n")
    top = ("@ti.kernel\ndef k(p: ti.template(), gx: float, f: ti.template()):\n"
           "    if ti.static(f):\n        body(p, gx)\n")
    inner = "@ti.kernel\ndef k(p: ti.template(), gx: float):\n    for s in range(2):\n        body(p, gx)\n"
    assert vectors_handed_to_loops(func + top) == [("k", "g", 3)]
    assert vectors_handed_to_loops(func + inner) == []


def test_no_kernel_hands_a_vector_to_its_parallel_loop():
    funcs = {n.name: n for path in SOURCES for n in ast.walk(ast.parse(path.read_text()))
             if _is_func(n)}
    found = {str(path.name): vectors_handed_to_loops(path.read_text(), funcs) for path in SOURCES}
    assert {k: v for k, v in found.items() if v} == {}
