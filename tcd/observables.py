"""Reductions of a simulation state to numbers (NumPy, on host copies).

Packing fraction counts, for each sphere, the exact volume of the part of it that lies
between two horizontal planes (spherical caps), inside a cylinder of radius R; spheres are
assumed inside the cylinder (the mould holds them).
"""
from __future__ import annotations

import math

import numpy as np

#: the paper's Table 2: mean of the 5 cores tested (MPa, mm)
PAPER_EXPERIMENT = {"tau_peak_MPa": 0.898, "d_peak_mm": 2.37}
#: the paper's Table 2: mean of its 5 LMGC90 samples (MPa, mm)
PAPER_SIMULATION = {"tau_peak_MPa": 0.837, "d_peak_mm": 2.2}
#: the paper's Leutner test (section 3.4): a 150 mm by 120 mm core sheared at 50 mm/min to
#: 2.5 mm. Table 2's experiments are that test's; a run of another test is not compared with them
PAPER_TEST = {"velocity_mm_per_min": 50.0, "displacement_mm": 2.5, "diameter_mm": 150.0,
              "height_mm": 120.0}
#: relative tolerance of the speed and the mould's diameter, and of the sample's height (a
#: prepared sample settles below its mould: the study's are 118.2-118.9 mm), in `paper_test_differences`
PAPER_TEST_TOLERANCE = {"velocity_mm_per_min": 0.01, "diameter_mm": 0.01, "height_mm": 0.05}
#: the per-sample results a study averages
STUDY_KEYS = ("tau_peak_MPa", "d_peak_mm", "residual_MPa")


def kinetic_energy_of(v, w, inv_mass, inv_inertia) -> float:
    """Translational + rotational kinetic energy (J) of bodies of inverse masses `inv_mass`
    and inverse moments of inertia `inv_inertia` (a simulation's own, loaded states included);
    a kinematic body (inverse mass 0: infinite mass, driven) carries none."""
    inv_mass, inv_inertia = np.asarray(inv_mass, float), np.asarray(inv_inertia, float)
    m = np.divide(1.0, inv_mass, out=np.zeros_like(inv_mass), where=inv_mass > 0)
    inertia = np.divide(1.0, inv_inertia, out=np.zeros_like(inv_inertia), where=inv_inertia > 0)
    return float(0.5 * np.sum(m * np.sum(v**2, axis=1)) + 0.5 * np.sum(inertia * np.sum(w**2, axis=1)))


def spin_about_axis(x, v, w, inv_mass, inv_inertia, centre=(0.0, 0.0)) -> float:
    """The free bodies' rotation about the vertical axis through `centre` (x, y), as one rigid
    body would turn with their angular momentum about it (rad/s, counterclockwise seen from
    above): L_z / I_z, with L_z = sum m ((x - c) x v)_z + I w_z and I_z = sum m rho^2 + I
    (rho the distance from the axis; a sphere's own inertia I about its centre). 0 when no
    body is free."""
    inv_mass, inv_inertia = np.asarray(inv_mass, float), np.asarray(inv_inertia, float)
    m = np.divide(1.0, inv_mass, out=np.zeros_like(inv_mass), where=inv_mass > 0)
    inertia = np.divide(1.0, inv_inertia, out=np.zeros_like(inv_inertia), where=inv_inertia > 0)
    dx, dy = x[:, 0] - centre[0], x[:, 1] - centre[1]
    lz = np.sum(m * (dx * v[:, 1] - dy * v[:, 0])) + np.sum(inertia * w[:, 2])
    iz = np.sum(m * (dx**2 + dy**2)) + np.sum(inertia)
    return float(lz / iz) if iz > 0 else 0.0


def slab_volume(z, r, z0: float, z1: float) -> np.ndarray:
    """Volume of each sphere (centre height z, radius r) lying between z0 and z1 (m^3)."""
    def below(h):  # volume of the sphere below height h
        t = np.clip(h - (z - r), 0.0, 2 * r)
        return math.pi * t**2 * (3 * r - t) / 3.0
    return below(z1) - below(z0)


def packing_fraction(x, r, radius: float, z0: float, z1: float) -> float:
    """Solid fraction of the cylinder of `radius` between z0 and z1."""
    if z1 <= z0:
        raise ValueError("packing fraction needs z1 > z0")
    solid = float(np.sum(slab_volume(x[:, 2], r, z0, z1)))
    return solid / (math.pi * radius**2 * (z1 - z0))


def outside(x, r, radius: float, z0: float, z1: float, axis=(0.0, 0.0)) -> int:
    """Spheres that poke through a mould (a vertical cylinder of `radius` about `axis`, x and
    y) or its plates at z0 and z1 by more than 1 % of the smallest diameter."""
    x, r = np.asarray(x), np.asarray(r)
    slack = 0.01 * 2 * float(r.min())
    rho = np.hypot(x[:, 0] - axis[0], x[:, 1] - axis[1])
    return int(np.count_nonzero((rho + r > radius + slack) | (x[:, 2] - r < z0 - slack)
                                | (x[:, 2] + r > z1 + slack)))


def layer_highest(x, r, layer) -> list[float]:
    """Height of each layer's highest grain top (m): where a plate lowered onto the layer would
    rest."""
    tops = np.asarray(x)[:, 2] + np.asarray(r)
    return [float(tops[layer == L].max()) for L in sorted(set(np.asarray(layer).tolist()))]


def layer_tops(x, r, layer) -> list[float]:
    """Height of the top of each layer: 99th percentile of particle tops, robust to a few
    grains that ride up (m)."""
    out = []
    for L in sorted(set(np.asarray(layer).tolist())):
        sel = layer == L
        out.append(float(np.percentile(x[sel, 2] + r[sel], 99.0)))
    return out


def layer_interface(x, r, layer, lower: int, upper: int) -> float:
    """Height of the interface between two layers (m): the plane z_b where the volume of the
    lower layer's spheres above z_b equals the volume of the upper layer's spheres below it
    (their interpenetration is split evenly). Bisection on a monotone function."""
    lo_sel, up_sel = layer == lower, layer == upper
    zl, rl = x[lo_sel, 2], r[lo_sel]
    zu, ru = x[up_sel, 2], r[up_sel]
    big = 1e9

    def excess(z):
        return (float(np.sum(slab_volume(zl, rl, z, big)))
                - float(np.sum(slab_volume(zu, ru, -big, z))))
    a = float(min((zl - rl).min(), (zu - ru).min()))
    b = float(max((zl + rl).max(), (zu + ru).max()))
    for _ in range(60):
        m = 0.5 * (a + b)
        if excess(m) > 0.0:
            a = m
        else:
            b = m
    return 0.5 * (a + b)


def carries_force(i, j, impulse, x) -> np.ndarray:
    """Which contacts carried a force over the last step: particle-particle contacts whose
    impulse on j (global, as `Simulation.contact_arrays` and the states files give it) has a
    positive component along x_j - x_i, the two grains pressed together (a Coulomb contact
    with no normal impulse has none at all). Wall contacts (j >= n) are False."""
    i, j = np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64)
    x = np.asarray(x, dtype=float)
    pp = j < len(x)
    out = np.zeros(len(j), bool)
    branch = x[j[pp]] - x[i[pp]]
    out[pp] = np.einsum("ki,ki->k", np.asarray(impulse, dtype=float).reshape(-1, 3)[pp], branch) > 0.0
    return out


def bond_gap_middle(x, r, i, j) -> np.ndarray:
    """The middle of the gap between particles i and j, x_i + (r_i + g/2) n with n the unit
    vector from i to j and g the gap: where the solver records a bond's breakage
    (`bonds/broken_position`) and where a bond's force acts. It is the centres' midpoint moved
    by (r_i - r_j)/2 along n."""
    x, r = np.asarray(x, dtype=float), np.asarray(r, dtype=float)
    i, j = np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64)
    branch = x[j] - x[i]
    dist = np.linalg.norm(branch, axis=1)
    gap = dist - r[i] - r[j]
    n = branch / np.where(dist > 0.0, dist, 1.0)[:, None]
    return x[i] + (r[i] + 0.5 * gap)[:, None] * n


def coordination_number(i, j, n: int, loaded=None) -> float:
    """Mean number of particle-particle contacts per particle (walls excluded), 2 C / n.

    Without `loaded`: every listed contact, i.e. every pair within the alert distance
    (touching or not; 5.01 on the shipped seed-1 sample). With `loaded` (`carries_force`'s
    mask): only the contacts that carried a force over the last step, the coordination number
    of granular mechanics (4.01 there; rattlers are counted in n)."""
    pp = np.asarray(j) < n
    if loaded is not None:
        pp &= np.asarray(loaded, bool)
    return 2.0 * np.count_nonzero(pp) / n if n else 0.0


def max_overlap(gap) -> float:
    gap = np.asarray(gap)
    return float(max(0.0, -gap.min())) if gap.size else 0.0


def smooth(y, x, window) -> np.ndarray:
    """Centred moving average of `y` over ``|x_j - x_i| <= window / 2`` (window in x units).

    x may be non-uniform (sorted internally when it is not ascending); near the ends the
    average uses the points available. NaN values of y are left out of the averages. A window
    <= 0 returns a copy of y.
    """
    y = np.asarray(y, dtype=float)
    x = np.asarray(x, dtype=float)
    if y.shape != x.shape or y.ndim != 1:
        raise ValueError(f"smooth: x and y must be 1-D of the same length, got {x.shape} "
                         f"and {y.shape}")
    if not window > 0 or y.size == 0:
        return y.copy()
    order = np.argsort(x, kind="stable")
    xs, ys = x[order], y[order]
    finite = np.isfinite(ys)
    csum = np.concatenate([[0.0], np.cumsum(np.where(finite, ys, 0.0))])
    ccount = np.concatenate([[0], np.cumsum(finite)])
    lo = np.searchsorted(xs, xs - 0.5 * window, side="left")
    hi = np.searchsorted(xs, xs + 0.5 * window, side="right")
    count = ccount[hi] - ccount[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (csum[hi] - csum[lo]) / count
    out = np.empty_like(mean)
    out[order] = np.where(count > 0, mean, np.nan)
    return out


def peak_of(displacement, stress, window) -> tuple[float, float, int]:
    """(peak of the smoothed stress, displacement there, its index).

    Among equal maxima the last index wins, so a monotonic curve peaks at its last point.
    """
    displacement = np.asarray(displacement, dtype=float)
    smoothed = smooth(stress, displacement, window)
    if smoothed.size == 0 or not np.any(np.isfinite(smoothed)):
        raise ValueError("peak_of: no finite stress values")
    top = np.nanmax(smoothed)
    index = int(np.flatnonzero(smoothed == top)[-1])
    return float(top), float(displacement[index]), index


def peak_at_end(displacement, d_peak, window) -> bool:
    """Whether a curve's peak (:func:`peak_of`, at `d_peak`) lies within half a smoothing
    `window` of its last point, so that the average the peak is (:func:`smooth`) reaches the
    end of the curve: the stress was not seen to fall from it by the end of the series, and the
    peak is the end of a curve that may still rise (no failure reached), a lower bound of what
    a longer test would give. Same units for the three."""
    d = np.asarray(displacement, dtype=float)
    d = d[np.isfinite(d)]
    return bool(d.size) and float(d.max()) - float(d_peak) < 0.5 * float(window)


def as_number(value) -> float:
    """A summary entry as a float; None (JSON null) and junk become NaN."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def paper_test_differences(velocity_mm_per_min: float, displacement_mm: float,
                           diameters_mm=(), heights_mm=()) -> list[str]:
    """How a shear test differs from the paper's Leutner test (:data:`PAPER_TEST`), one phrase
    each; [] when it is that test. `diameters_mm` and `heights_mm`: the samples' moulds and
    heights (NaN or None where a sample does not say: not counted). A test that stops before
    the experiments' peak (2.37 mm) differs; one that goes beyond 2.5 mm does not."""
    out = []
    tol, paper = PAPER_TEST_TOLERANCE, PAPER_TEST
    v = as_number(velocity_mm_per_min)
    if not abs(v / paper["velocity_mm_per_min"] - 1.0) <= tol["velocity_mm_per_min"]:
        out.append(f"a shear at {v:g} mm/min (the paper's: {paper['velocity_mm_per_min']:g})")
    d = as_number(displacement_mm)
    if not d >= PAPER_EXPERIMENT["d_peak_mm"]:
        out.append(f"a shear to {d:g} mm (the paper's: to {paper['displacement_mm']:g} mm; "
                   f"the experiments' peak is at {PAPER_EXPERIMENT['d_peak_mm']:g} mm)")
    for key, values, what in (("diameter_mm", diameters_mm, "a mould of"),
                              ("height_mm", heights_mm, "a sample height of")):
        values = np.array([as_number(x) for x in values], dtype=float)
        values = values[np.isfinite(values)]
        off = values[np.abs(values / paper[key] - 1.0) > tol[key]]
        if off.size:
            shown = (f"{off.min():.4g}" if np.ptp(off) <= 1e-9 * abs(off.max())
                     else f"{off.min():.4g}-{off.max():.4g}")
            out.append(f"{what} {shown} mm (the paper's: {paper[key]:g} mm)")
    return out


def study_statistics(samples, experiment=None) -> tuple[dict, dict, dict]:
    """(mean, population std, relative error of the mean) of a study's samples.

    Each of :data:`STUDY_KEYS` is averaged over the samples where it is a finite number (a
    sample without a peak, or with null / NaN, is left out of that key only) and is absent from
    mean and std when no sample has it. The relative errors ``tau_peak`` and ``d_peak`` compare
    the mean with `experiment` (default: the paper's experiments) and need both means.
    The samples are taken in the order of their seeds (those without one last), so that a
    study run as `--seeds 5,4,3,2,1`, split across runs, or merged by `tcd figures` has the
    same statistics to the last bit (a sum's rounding depends on its order).
    """
    experiment = {**PAPER_EXPERIMENT, **(experiment or {})}
    samples = sorted(samples, key=lambda smp: (not isinstance(smp.get("seed"), int),
                                               smp.get("seed") if isinstance(smp.get("seed"), int) else 0))
    mean, std = {}, {}
    for key in STUDY_KEYS:
        values = np.array([as_number(smp.get(key)) for smp in samples], dtype=float)
        values = values[np.isfinite(values)]
        if values.size:
            mean[key], std[key] = float(values.mean()), float(values.std())
    relative = {}
    if "tau_peak_MPa" in mean and "d_peak_mm" in mean:
        relative = {"tau_peak": mean["tau_peak_MPa"] / experiment["tau_peak_MPa"] - 1.0,
                    "d_peak": mean["d_peak_mm"] / experiment["d_peak_mm"] - 1.0}
    return mean, std, relative
