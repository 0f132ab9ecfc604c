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


def vectors_handed_to_loops(source: str):
    """(kernel, name, line) for each vector set at a kernel's top level and used by a later
    top-level loop."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not _is_kernel(node):
            continue
        vectors = {}
        for st in node.body:
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


def test_no_kernel_hands_a_vector_to_its_parallel_loop():
    found = {str(path.name): vectors_handed_to_loops(path.read_text()) for path in SOURCES}
    assert {k: v for k, v in found.items() if v} == {}
