"""Local contact laws: pure Taichi functions, each with a NumPy twin used as the test oracle.

Conventions (PHYSICS.md sections 2-5): for a contact between body i and body j, the normal n
points from i to j, the impulse R (N s, a global 3-vector) acts on j and -R on i, R.n >= 0 is
repulsive, and U is the velocity of j relative to i at the contact point. The Delassus block of
a sphere pair is diagonal in the local frame: W_nn on the normal, W_tt (isotropic) in the
tangent plane, so every local problem is solved in closed form.
"""

import math

import numpy as np
import taichi as ti


# --- frictional contact: Signorini + Coulomb (section 3) -------------------------------------
@ti.func
def signorini_coulomb(ufn, uft, rhs_n, inv_wnn, inv_wtt, mu):
    """Exact local solution given the free velocity (ufn, uft) and gap term rhs_n = g/(theta H),
    the Delassus diagonal given by its inverses 1/W_nn, 1/W_tt.

    Returns (R_n, R_T) with R_T a vector in the tangent plane. The inverses come from the
    contact's record, off the chain of body velocities that one Gauss-Seidel visit waits on
    from the one before; multiplying by them instead of dividing shortens that chain (measured,
    session 16, impact step of benchmarks/solver_convergence.py: 36.6 -> 33.2 ns per contact
    update with NNCG, 28.6 -> 26.3 plain; the same residuals to three digits)."""
    rn = ti.max(0.0, -(ufn + rhs_n) * inv_wnn)
    rt = -uft * inv_wtt
    # squared comparison: the square root is only paid when the contact slides
    nt2 = rt.norm_sqr()
    limit = mu * rn
    if nt2 > limit * limit:
        scale = 0.0
        if nt2 > 0.0:
            scale = limit / ti.sqrt(nt2)
        rt *= scale
    return rn, rt


def signorini_coulomb_np(ufn, uft, rhs_n, inv_wnn, inv_wtt, mu):
    rn = max(0.0, -(ufn + rhs_n) * inv_wnn)
    rt = -np.asarray(uft, dtype=float) * inv_wtt
    nt = float(np.linalg.norm(rt))
    if nt > mu * rn:
        rt = rt * (mu * rn / nt if nt > 0 else 0.0)
    return rn, rt


# --- bonded contact: bilateral with extra diagonal compliance (section 4) --------------------
@ti.func
def bonded(ufn, uft, rhs_n, rhs_t, wnn, wtt, cn, ct):
    """(W + c) R = -(U_f + delta_beg / (theta H)), normal and tangent, no projection."""
    rn = -(ufn + rhs_n) / (wnn + cn)
    rt = -(uft + rhs_t) / (wtt + ct)
    return rn, rt


def bonded_np(ufn, uft, rhs_n, rhs_t, wnn, wtt, cn, ct):
    rn = -(ufn + rhs_n) / (wnn + cn)
    rt = -(np.asarray(uft, dtype=float) + np.asarray(rhs_t, dtype=float)) / (wtt + ct)
    return rn, rt


# --- Burgers rheology -------------------------------------------------------------------------
def creep_compliance(t, k_m, eta_m, k_k, eta_k):
    """J(t) = 1/K_m + t/eta_m + (1/K_k)(1 - exp(-t/t_r)), t_r = eta_k/K_k (m/N)."""
    t = np.asarray(t, dtype=float)
    return 1.0 / k_m + t / eta_m + (1.0 - np.exp(-t * k_k / eta_k)) / k_k


@ti.func
def creep_compliance_ti(t, k_m, eta_m, k_k, eta_k):
    return 1.0 / k_m + t / eta_m + (1.0 - ti.exp(-t * k_k / eta_k)) / k_k


def burgers_step_compliance(h, k_m, eta_m, k_k, eta_k):
    """Compliance of one implicit-Euler step of the Burgers model: 1/K_m + H/eta_m + H/(eta_k + H K_k)."""
    return 1.0 / k_m + h / eta_m + h / (eta_k + h * k_k)


def burgers_relaxation_np(delta0, times, h, k_m, eta_m, k_k, eta_k):
    """Force under a displacement held at delta0 from t = 0, integrating the same implicit
    scheme as the solver (oracle for the relaxation test) -- and the exact continuous answer.

    Returns (force_discrete, force_exact) at `times` (multiples of h)."""
    steps = int(round(times[-1] / h))
    c = burgers_step_compliance(h, k_m, eta_m, k_k, eta_k)
    dd = dk = 0.0
    out = []
    for _ in range(steps):
        off = dd + eta_k * dk / (eta_k + h * k_k)
        f = (delta0 - off) / c
        dd += h * f / eta_m
        dk = (eta_k * dk + h * f) / (eta_k + h * k_k)
        out.append(f)
    f_disc = np.asarray(out)[np.round(np.asarray(times) / h).astype(int) - 1]
    return f_disc, burgers_relaxation_exact(delta0, np.asarray(times), k_m, eta_m, k_k, eta_k)


def burgers_relaxation_exact(delta0, t, k_m, eta_m, k_k, eta_k):
    """Closed-form relaxation force of a Burgers element under a step displacement delta0.

    State: Maxwell spring+dashpot in series with Kelvin-Voigt. With F the common force,
    dk the Kelvin displacement: delta0 = F/K_m + d_dash + dk, dF/dt and ddk/dt linear ODEs.
    Solved as a 2x2 linear system x' = A x, x = (F, dk)."""
    # d_dash' = F/eta_m ; dk' = (F - K_k dk)/eta_k ; 0 = F'/K_m + d_dash' + dk'
    a = np.array([[-k_m / eta_m - k_m / eta_k, k_m * k_k / eta_k],
                  [1.0 / eta_k, -k_k / eta_k]])
    x0 = np.array([k_m * delta0, 0.0])
    w, v = np.linalg.eig(a)
    coef = np.linalg.solve(v, x0)
    t = np.asarray(t, dtype=float)
    xs = (v[:, :, None] * (coef[:, None] * np.exp(w[:, None] * t[None, :]))[None, :, :]).sum(axis=1)
    return np.real(xs[0])


def yield_area(ri, rj):
    """Smaller projected area pi min(r_i, r_j)^2 (m^2)."""
    return math.pi * min(ri, rj) ** 2
