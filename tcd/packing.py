"""Seeded particle generation from the paper's size tables (NumPy only).

Sizes are drawn by NUMBER fraction (PHYSICS.md section 7): each diameter class gets
round(fraction * count) spheres, the rounding remainder going to the classes with the largest
fractional parts, so a given count always yields the same class counts. Positions are random
distinct sites of a cubic lattice inside a vertical column, each site nudged by a small seeded
horizontal offset so that spheres stacked on one lattice column do not fall exactly head-on.
"""
from __future__ import annotations

import math

import numpy as np

#: diameters (m) and number fractions of the two courses (paper Table 1)
DIAMETERS = np.array([2.0, 5.6, 8.0, 11.2, 16.0]) * 1e-3
COURSES = {
    "binder": np.array([22.9, 20.1, 24.0, 29.8, 3.2]) / 100.0,
    "surface": np.array([28.4, 32.4, 36.6, 2.7, 0.0]) / 100.0,
}


def course_fractions(course: str) -> np.ndarray:
    if course not in COURSES:
        raise ValueError(f"unknown course {course!r}: expected one of {sorted(COURSES)}")
    f = COURSES[course]
    return f / f.sum()


def class_counts(course: str, count: int) -> np.ndarray:
    """Number of spheres of each diameter class for `count` spheres (largest remainder)."""
    if count < 0:
        raise ValueError(f"particle count must be >= 0, got {count}")
    f = course_fractions(course) * count
    n = np.floor(f).astype(int)
    rest = count - n.sum()
    order = np.argsort(-(f - n), kind="stable")
    n[order[:rest]] += 1
    return n


def mean_sphere_volume(course: str) -> float:
    f = course_fractions(course)
    return float(np.sum(f * math.pi / 6.0 * DIAMETERS**3))


def count_for_layer(course: str, diameter: float, height: float, packing_fraction: float) -> int:
    """Spheres needed to fill a cylinder (diameter, height) at the given packing fraction."""
    if diameter <= 0 or height <= 0:
        raise ValueError("layer diameter and height must be positive")
    if not 0 < packing_fraction < 0.75:
        raise ValueError(f"packing fraction {packing_fraction} outside (0, 0.75)")
    volume = math.pi * diameter**2 / 4.0 * height
    return int(round(packing_fraction * volume / mean_sphere_volume(course)))


def course_radii(course: str, count: int, rng: np.random.Generator) -> np.ndarray:
    """Radii (m) of `count` spheres of a course, class counts exact, order shuffled by `rng`."""
    n = class_counts(course, count)
    radii = np.repeat(DIAMETERS / 2.0, n)
    rng.shuffle(radii)
    return radii


class ColumnTooTall(ValueError):
    """lattice_column: the spheres need a taller column than max_height allows."""


#: the most lattice spacings in a pouring column's radius (about 3e7 sites per level)
MAX_SITES_ACROSS = 3000


def lattice_column(radii: np.ndarray, column_diameter: float, z0: float, rng: np.random.Generator,
                   *, max_height: float = 1.6, jitter: float = 2e-4,
                   spacing: float | None = None) -> np.ndarray:
    """Place spheres at random distinct sites of a cubic lattice inside a vertical column.

    The lattice spacing is the largest diameter plus `jitter` on each side (so no two spheres
    overlap whatever the offsets); a site is inside the column when a sphere of the largest size
    centred there stays inside `column_diameter`. Each sphere gets a uniform horizontal offset in
    [-jitter, jitter] on x and y (symmetry breaking). The column has just enough lattice levels for all spheres;
    the sites used among them are random (the radii come in random order), and the
    returned sites are sorted by level, bottom first.
    Returns positions (count, 3) with the column axis at x = y = 0 and the lowest centres at
    z0 + spacing / 2.
    """
    radii = np.asarray(radii, dtype=float)
    if radii.size == 0:
        return np.zeros((0, 3))
    if np.any(radii <= 0):
        raise ValueError("sphere radii must be positive")
    rmax = float(radii.max())
    a = spacing if spacing is not None else 2.0 * rmax + 2.0 * jitter
    half = column_diameter / 2.0 - rmax - jitter
    if half <= 0:
        raise ValueError(f"column diameter {column_diameter} m is smaller than the largest sphere")
    if not half / a <= MAX_SITES_ACROSS:
        raise ValueError(f"column diameter {column_diameter:g} m is {half / a:.3g} lattice "
                         f"spacings ({a:g} m) in radius: at most {MAX_SITES_ACROSS} (a wider "
                         "column is not a sample tcd can pour)")
    k = int(math.floor(half / a)) + 1
    g = np.arange(-k, k + 1) * a
    gx, gy = np.meshgrid(g, g, indexing="ij")
    inside = gx**2 + gy**2 <= half**2
    sites_xy = np.stack([gx[inside], gy[inside]], axis=1)
    per_level = len(sites_xy)
    if per_level == 0:
        raise ValueError("column too narrow for one lattice site")
    levels = int(math.ceil(len(radii) / per_level))
    height = levels * a
    if height > max_height:
        raise ColumnTooTall(f"{len(radii)} spheres need a {height:.3f} m column, above max_height "
                         f"{max_height} m")
    sites = np.concatenate([np.column_stack([sites_xy, np.full(per_level, z0 + (l + 0.5) * a)])
                            for l in range(levels)])
    chosen = np.sort(rng.choice(len(sites), size=len(radii), replace=False))
    pos = sites[chosen]
    pos[:, :2] += rng.uniform(-jitter, jitter, size=(len(radii), 2))
    # radii are already in random order; positions stay sorted bottom-up so that particle
    # index follows height, which makes Gauss-Seidel sweeps in index order propagate loads
    return pos
