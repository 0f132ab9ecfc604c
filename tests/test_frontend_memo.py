"""tcd.backend.memoise_frontend: the memoised pieces of Taichi's Python frontend give exactly
what Taichi's own functions give, so the kernels' IR, the offline cache's keys and the error
messages do not change (the memo only saves the time of rendering them again)."""
import ast
import inspect

from taichi.lang import kernel_impl
from taichi.lang.ast import ast_transformer_utils as utils

from tcd import backend as tcd_backend
from tcd import partitioned, solver


def _tree_and_context(function):
    """The AST and frontend context Taichi builds for a kernel or a ti.func (template values
    are only stored in the context, not read, so placeholders do)."""
    if hasattr(function, "_primal"):
        primal = function._primal
        return kernel_impl._get_tree_and_ctx(primal, args=[None] * len(primal.arguments))
    func = function.func
    return kernel_impl._get_tree_and_ctx(func, is_kernel=False, args=[None] * len(func.arguments))


def test_memo_is_installed_once_by_init(backend):
    memo = utils.ASTTransformerContext.get_pos_info
    assert getattr(memo, "_tcd_memo", False)
    assert tcd_backend.memoise_frontend() and utils.ASTTransformerContext.get_pos_info is memo


def test_memoised_debug_info_equals_taichi_rendering_for_every_node(backend):
    original = utils.ASTTransformerContext.get_pos_info.__wrapped__
    memo = utils.ASTTransformerContext.get_pos_info
    kinds = set()
    total = 0
    for kernel in (solver.nlgs_serial, partitioned.nlgs_partitioned, solver.integrate,
                   solver.contact_law, solver.bond_law, solver.solve_particle_bonds,
                   solver.bonds_prepare, solver.colour_greedy):
        tree, ctx = _tree_and_context(kernel)
        nodes = [n for n in ast.walk(tree) if hasattr(n, "lineno")]
        total += len(nodes)
        for node in nodes:
            want = original(ctx, node)
            got = memo(ctx, node)
            assert got == want, ast.dump(node)[:200]
            assert memo(ctx, node) is got                # the second call is the memo's
            kinds.add(type(node).__name__)
        # the same node positions under another instantiation's context give the same text
        _, again = _tree_and_context(kernel)
        assert all(memo(again, n) == original(again, n) for n in nodes[:200])
    assert total > 1000
    assert {"For", "If", "While", "FunctionDef", "Assign", "Call"} <= kinds


def test_memoised_source_lines_equal_inspect(backend):
    for kernel in (solver.nlgs_serial, solver.step_end):
        func = kernel._primal.func
        want = inspect.getsourcelines(func)
        first = kernel_impl.getsourcelines(func)
        second = kernel_impl.getsourcelines(func)
        assert first == second and list(first[0]) == list(want[0]) and first[1] == want[1]
        first[0].append("mutated by a caller")            # a caller's list is its own
        assert kernel_impl.getsourcelines(func)[0] == list(want[0])
