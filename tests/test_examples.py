"""The scripts of examples/ (docs/scripting.md) against the closed forms they print: each
example's run() on the session's backend, so that the scripting guide cannot drift from the API."""
import importlib.util
import math
import pathlib

import numpy as np
import pytest

from tcd import io

ROOT = pathlib.Path(__file__).resolve().parents[1]


def example(name):
    spec = importlib.util.spec_from_file_location(f"example_{name}",
                                                  ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("theta, mu, rolls", [(20.0, 0.3, True), (30.0, 0.1, False)])
def test_the_incline_example_rolls_or_slips_as_the_closed_forms(theta, mu, rolls, tol):
    o = example("incline").run(theta, mu, time=0.1)
    assert o["rolls"] == rolls
    rtol = max(tol, 1e-6)
    assert o["speed_down_slope"] == pytest.approx(o["expected_speed"], rel=rtol)
    assert o["spin_times_radius"] == pytest.approx(o["expected_spin_times_radius"], rel=rtol)
    assert abs(o["speed_off_plane"]) < 1e-5 * o["expected_speed"]
    np.testing.assert_allclose(o["wall_force"], o["expected_wall_force"], rtol=rtol,
                               atol=rtol * np.linalg.norm(o["expected_wall_force"]))


def test_the_bonded_creep_example_follows_F_J_t(precision):
    creep = example("bonded_creep")
    o = creep.run(force=2.0, time=12.0, mode="burgers")
    assert len(o["rows"]) == 12 and o["bonds_intact"] == 1
    worst = max(abs(d / e - 1.0) for _, d, e in o["rows"])
    # f64: 4e-5 measured; f32 resolves an 8 mm position to 1e-9 m, 1e-3 of the opening
    assert worst < (1e-3 if precision == "f64" else 1e-2)
    # the example's own oracle is PHYSICS.md's J(t): J(0) = 1/K_m, the flow slope 1/eta_m
    J = creep.creep_compliance
    assert float(J(0.0)) == pytest.approx(5e-7, rel=1e-15)
    assert float(J(1001.0) - J(1000.0)) == pytest.approx(1 / 2e7, rel=1e-9)


def test_the_pour_example_settles_and_the_floor_carries_the_weight(tmp_path):
    out = tmp_path / "pour_states.h5"
    o = example("pour").run(particles=300, scale=0.5, seed=1, out=str(out))
    assert o["settled"] and o["time"] < 1.0
    # at rest in a frictionless mould the floor carries the whole weight (measured 1.0001)
    assert -o["floor_force"] / o["weight"] == pytest.approx(1.0, abs=0.01)
    assert o["mould_vertical_force"] == 0.0
    assert o["outside"] == 0 and o["max_overlap_ratio"] < 0.01
    assert 0.4 < o["packing_fraction"] < 0.65
    # the snapshots are a tcd states file: every 0.1 s and the settled state last
    frames = io.frame_count(out)
    assert frames == math.floor(o["time"] / 0.1 + 1e-9) + 1
    last = io.read_frame(out, -1)
    assert last["particles/x"].shape == (300, 3)
