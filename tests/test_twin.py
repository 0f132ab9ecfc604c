"""Scaled-down twin of the paper's study (scenarios/twin.toml): the invariants of the prepared
sample (issue 5) and of the Leutner shear (issue 6), on a few hundred spheres.

The twin is the paper's sample scaled down (grain sizes x 0.4; the mould and the layers shrunk
further, to 24 mm and two 8 mm layers, a 16 mm sample, to keep a few hundred grains) at the
paper's time step; the vibration (scaled with the sizes) and the shear rate (faster, so that the
test runs in a few minutes) differ too. Its layers are 1.25 largest grains thick: its binder
course jams above its target, so its layers meet 8 mm only on the equal-volume reading (README,
"The five prepared samples"). It is run once per session
through `tcd run`, and every check reads the files a user would read.
"""
import json
import pathlib

import numpy as np
import pytest

from conftest import run_tcd
from tcd import io

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    out = tmp_path_factory.mktemp("twin") / "out"
    assert run_tcd(["run", str(ROOT / "scenarios" / "twin.toml"), "--out", str(out)]) == 0
    sample = json.loads((out / "sample_1" / "summary.json").read_text())
    return out, sample["stages"]["0:prepare"], sample["stages"]["1:shear"]


# -- issue 5: the prepared sample ----------------------------------------------------------------
def test_twin_sample_dimensions_and_layers(twin):
    _, prep, _ = twin
    assert prep["diameter_mm"] == pytest.approx(24.0)
    # the plate stops where the rigid grains jam: the twin's narrow mould (3.75 largest
    # diameters across, against 9.4 in the paper's) packs a little looser near its wall
    assert 16.0 - 0.05 <= prep["sample_height_mm"] <= 16.0 * 1.05
    # two layers of 8 mm within the scaled tolerance (2 mm in 60 mm for the paper's sample)
    for h in prep["layer_heights_mm"]:
        assert h == pytest.approx(8.0, abs=2.0 * 8.0 / 60.0 + 0.3)
    assert len(prep["particles_per_layer"]) == 2 and min(prep["particles_per_layer"]) > 50
    # the interface diagnostics add up: lifts fill the sample, their own-grain packings
    # average to the overall one, and no more surface grains sank than the surface course has
    assert sum(prep["course_lift_heights_mm"]) == pytest.approx(prep["sample_height_mm"], rel=1e-9)
    mean = np.dot(prep["course_lift_heights_mm"], prep["course_packing_fraction_per_lift"]) / prep["sample_height_mm"]
    assert mean == pytest.approx(prep["packing_fraction"], abs=0.01)
    assert 0 <= prep["grains_in_lower_course"][1] <= prep["particles_per_layer"][1]
    assert prep["grains_in_lower_course"][0] == 0


def test_twin_packing_overlap_and_containment(twin):
    _, prep, _ = twin
    assert 0.57 <= prep["packing_fraction"] <= 0.61
    assert prep["outside"] == 0
    assert prep["max_overlap_ratio"] < 0.01
    assert prep["coordination_number"] > 3.0


def test_twin_grains_top_and_packing_below_it(twin):
    """The sample read by its grains: their highest top lies between the surface course's
    99th-percentile top and the plate (no grain through it), and the packing over that height
    holds the same sphere volume as the packing between the plates."""
    _, prep, _ = twin
    H, top = prep["sample_height_mm"], prep["highest_grain_top_mm"]
    slack = 0.01 * 2 * 0.4                        # 1 % of the twin's smallest diameter (mm)
    assert prep["layer_tops_mm"][-1] <= top <= H + slack
    assert prep["top_plate_gap_mm"] == pytest.approx(H - top, abs=1e-9)
    assert prep["packing_fraction_below_highest_grain"] * min(top, H) == pytest.approx(
        prep["packing_fraction"] * H, rel=1e-9)


def test_twin_settles_and_names_where_it_fell_short(twin):
    """Every pour, hold and the confinement end because the grains settled (issue 5's stated
    criterion), not at their time limits; what the twin misses of its scenario (its courses
    jam above their targets, see the module's docstring) is named in `warnings`, and a sample
    taller than asked exactly when it is."""
    out, prep, _ = twin
    sample = json.loads((out / "sample_1" / "summary.json").read_text())
    settling = [rec for rec in sample["phases"] if rec["phase"] in ("pour", "hold", "confine")]
    assert len(settling) == 5 and all(rec["settled"] for rec in settling)
    assert not any("time limit" in w for w in prep["warnings"])
    taller = prep["sample_height_mm"] > 16.0 + 0.01 * 8.0
    assert any(w.startswith("the sample is") for w in prep["warnings"]) == taller
    for rec in sample["phases"]:
        if rec["phase"] == "hold":
            jammed = rec["plate_mm"] > 1e3 * rec["target"] + 0.08
            assert any(w.startswith(f"course {rec['layer']} ") for w in prep["warnings"]) == jammed


def test_twin_prepared_file_matches_summary(twin):
    out, prep, _ = twin
    arrays, meta = io.load_checkpoint(out / "sample_1" / "prepared.h5")
    assert len(arrays["particles/radius"]) == prep["particles"]
    x, r = arrays["particles/x"], arrays["particles/radius"]
    R = 0.5 * prep["diameter_mm"] * 1e-3
    slack = 0.01 * 2 * r.min()
    assert np.all(np.hypot(x[:, 0], x[:, 1]) + r <= R + slack)
    assert np.all(x[:, 2] - r >= -slack)
    assert np.all(x[:, 2] + r <= prep["sample_height_mm"] * 1e-3 + slack)


# -- issue 6: the shear ---------------------------------------------------------------------------
def test_twin_upper_half_moves_with_the_ring(twin):
    """The upper grains follow the ring; the lower ones move much less (the twin's rings are
    only 3.75 largest grains across, so the grains near the plane drag some lower ones)."""
    _, _, shear = twin
    assert shear["upper_mean_dx_over_ring"] > 0.8
    assert abs(shear["lower_mean_dx_over_ring"]) < 0.5 * shear["upper_mean_dx_over_ring"]


def test_twin_shear_is_quasi_static(twin):
    """The kinetic energy stays below 1 % of the work of the moving walls, and the sample does
    not turn as a whole about the mould's axis. (At tolerance 1e-4
    the unconverged bonds released energy: 1.7 % on this twin, with a peak of 1.85 MPa instead
    of 4.0: the ratio flags such runs.)"""
    _, _, shear = twin
    assert shear["wall_work_J"] > 0
    assert shear["kinetic_over_work_max"] < 0.01
    # nor does it turn about the mould's axis: with frictionless rings it spun up to 30 times
    # the ring's speed at its rim before the peak (session 48); with the rings' friction its
    # rim turns 0.0068 of the ring's travel by the peak
    assert shear["turn_rim_over_ring"] < 0.1
    assert "warnings" not in shear, shear.get("warnings")


def test_twin_bonds_break_most_near_the_plane(twin):
    """By the peak, broken bonds are commoner near the shear plane (within a quarter ring
    height) than far from it (beyond half a ring height). The twin's bonds are brittle (their
    yield displacement scales with the square of the sizes), so its failure is diffuse: after
    the peak nearly all of them break (at 2.5 mm, seeds 1-5: 0.99-1.00 near, 0.88-0.94 far),
    and only the bonds broken by the peak tell where failure formed (seeds 1-5, session 16,
    with the rings of sessions 1-31:
    0.97 / 0.97 / 0.97 / 0.77 / 0.93 near against 0.79 / 0.82 / 0.76 / 0.44 / 0.64 far)."""
    out, _, shear = twin
    series = io.read_series(out / "sample_1" / "shear_series.h5")
    t_peak = np.asarray(series["time"])[shear["peak_index"]]
    f = io.read_frame(out / "sample_1" / "states.h5", -1)
    state, i, j = f["bonds/state"], f["bonds/i"], f["bonds/j"]
    x = f["particles/x"]
    z = np.where(state != 0, f["bonds/broken_position"][:, 2], 0.5 * (x[i, 2] + x[j, 2]))
    z_i = shear["z_interface_mm"] * 1e-3
    ring = 4.0 * shear["near_plane_band_mm"] * 1e-3
    near, far = np.abs(z - z_i) < 0.25 * ring, np.abs(z - z_i) > 0.5 * ring
    broken = state != 0
    assert shear["bonds_broken"] == broken.sum() > 0.05 * len(state)
    assert near.sum() > 20 and far.sum() > 20
    by_peak = broken & (f["bonds/broken_time"] <= t_peak)
    assert by_peak[near].mean() > by_peak[far].mean() + 0.1


def test_twin_stress_rises_then_falls(twin):
    out, _, shear = twin
    s = io.read_series(out / "sample_1" / "shear_series.h5")
    d, tau = np.asarray(s["displacement"]), np.asarray(s["shear_stress"])
    k = shear["peak_index"]
    assert 0.1 * d[-1] < d[k] < 0.9 * d[-1]            # the peak is inside the test
    assert shear["tau_peak_MPa"] > 0
    early = tau[d < 0.25 * d[k]].mean()
    assert early < 0.6 * shear["tau_peak_MPa"] * 1e6    # a rise
    assert shear["residual_MPa"] < 0.9 * shear["tau_peak_MPa"]   # then a fall
