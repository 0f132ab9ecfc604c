"""The size tables and the lattice placement of the preparation (tcd/packing.py; PHYSICS.md
section 7) against hand-worked values (session 43's mutation audit)."""
import math

import numpy as np

from tcd import packing


def test_class_counts_give_the_rounding_remainder_to_the_largest_fractions():
    """10 binder spheres: 10 x (22.9, 20.1, 24.0, 29.8, 3.2) % = 2.29, 2.01, 2.40, 2.98, 0.32;
    floors (2, 2, 2, 2, 0) leave 2 spheres, which go to the largest remainders .98 and .40."""
    assert packing.class_counts("binder", 10).tolist() == [2, 2, 3, 3, 0]
    # surface, 7 spheres: 7 x (28.4, 32.4, 36.6, 2.7, 0)/100.1 = 1.986, 2.266, 2.559, 0.189, 0
    assert packing.class_counts("surface", 7).tolist() == [2, 2, 3, 0, 0]


def test_lattice_column_keeps_jittered_sites_inside_the_mould_and_apart():
    """Spheres of radius 1, jitter 0.1: spacing 2.2. A column of diameter 6.5 (half-width for a
    site 3.25 - 1 - 0.1 = 2.15 < 2.2) has only its axis site per level: three spheres stand on
    the axis at z0 + 1.1, 3.3, 5.5, never closer than their diameter."""
    rng = np.random.default_rng(7)
    x = packing.lattice_column(np.ones(3), 6.5, 0.5, rng, jitter=0.1, max_height=100.0)
    assert np.all(np.abs(x[:, :2]) <= 0.1)
    np.testing.assert_allclose(x[:, 2], 0.5 + np.array([1.1, 3.3, 5.5]), rtol=0, atol=1e-12)
    # a full level of a wider column: every pair is at least a diameter apart
    rng = np.random.default_rng(3)
    r = np.ones(200)
    x = packing.lattice_column(r, 12.0, 0.0, rng, jitter=0.1, max_height=100.0)
    d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=2) + 10 * np.eye(len(r))
    assert d.min() >= 2.0
    assert np.all(np.hypot(x[:, 0], x[:, 1]) + 1.0 <= 6.0 + (math.sqrt(2) - 1) * 0.1 + 1e-12)

