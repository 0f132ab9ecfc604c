"""The local Signorini-Coulomb law (PHYSICS.md section 3) on its own: the Taichi function the
Gauss-Seidel calls against its NumPy twin, and both against the conditions that define the
exact local solution (free velocity U_f, Delassus diagonal W_nn, W_tt given by its inverses):
  separating (U_f,n + g/(theta H) >= 0): R = 0;
  sticking: the end velocity U = U_f + W R is zero (normal: U_n = -g/(theta H)) and |R_T| <= mu R_n;
  sliding: R_n as when sticking, |R_T| = mu R_n, R_T opposite to the free tangential velocity."""
import numpy as np
import taichi as ti

from tcd import laws

CASES = 400


@ti.kernel
def law_kernel(inp: ti.types.ndarray(), out: ti.types.ndarray()):
    for k in range(inp.shape[0]):
        uft = ti.Vector([inp[k, 1], inp[k, 2], 0.0])
        rn, rt = laws.signorini_coulomb(inp[k, 0], uft, inp[k, 3], 1.0 / inp[k, 4],
                                        1.0 / inp[k, 5], inp[k, 6])
        out[k, 0] = rn
        out[k, 1] = rt[0]
        out[k, 2] = rt[1]
        out[k, 3] = rt[2]


def test_local_law_matches_its_numpy_twin_and_the_exact_local_solution(tol, precision):
    rng = np.random.default_rng(7)
    # columns: ufn, uft_x, uft_y, rhs_n, wnn, wtt, mu (normal along z, tangent plane x-y)
    inp = np.column_stack([rng.normal(0, 1, CASES), rng.normal(0, 1, CASES),
                           rng.normal(0, 1, CASES), rng.uniform(0, 0.3, CASES),
                           rng.uniform(0.5, 5, CASES), rng.uniform(0.5, 8, CASES),
                           rng.uniform(0, 1, CASES)])
    dtype = np.float64 if precision == "f64" else np.float32
    inp = inp.astype(dtype)
    out = np.zeros((CASES, 4), dtype)
    law_kernel(inp, out)
    kinds = set()
    for k, (ufn, ux, uy, rhs, wnn, wtt, mu) in enumerate(inp.astype(float)):
        rn, rt = laws.signorini_coulomb_np(ufn, [ux, uy, 0.0], rhs, 1.0 / wnn, 1.0 / wtt, mu)
        scale = 1.0 + abs(rn) + np.linalg.norm(rt)
        assert abs(out[k, 0] - rn) <= 10 * tol * scale
        np.testing.assert_allclose(out[k, 1:], rt, rtol=0, atol=10 * tol * scale)
        if ufn + rhs >= 0:
            kinds.add("separating")
            assert rn == 0 and np.linalg.norm(rt) == 0
            continue
        assert abs(ufn + wnn * rn + rhs) <= 10 * tol * (1 + abs(ufn))     # U_n = -g/(theta H)
        slip = np.array([ux, uy, 0.0]) + wtt * np.asarray(rt)
        if np.linalg.norm(slip) <= 10 * tol * (1 + abs(ux) + abs(uy)):
            kinds.add("sticking")
            assert np.linalg.norm(rt) <= mu * rn * (1 + 10 * tol)
        else:
            kinds.add("sliding")
            assert np.linalg.norm(rt) == np.float64(mu * rn) or \
                abs(np.linalg.norm(rt) - mu * rn) <= 10 * tol * scale
            # opposite to the free tangential velocity, and the slip goes along it
            free = np.array([ux, uy, 0.0]) / np.hypot(ux, uy)
            assert np.dot(np.asarray(rt), free) <= -(1 - 1e-3) * np.linalg.norm(rt)
            assert np.dot(slip, free) > 0
    assert kinds == {"separating", "sticking", "sliding"}
