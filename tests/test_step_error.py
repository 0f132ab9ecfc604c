"""benchmarks/step_error.py: the distance from a step stopped at the tolerance to the same step
solved to convergence, on a bonded pile sheared by a rough plate."""
import numpy as np
import pytest

from tcd import walls
from tcd.simulation import Simulation, SolverSettings


def sheared_pile():
    """A 4 x 4 x 3 lattice of touching spheres on a floor, bonded, under a rough top plate that
    moves along x."""
    r = 0.004
    g = np.arange(4) * 2 * r
    x = np.array([[a, b, r + c] for a in g for b in g for c in g[:3]])
    top = x[:, 2].max() + r
    plate = walls.plane((0, 0, top), (0, 0, -1), friction=0.7, motion="constant",
                        velocity=(0.05, 0.0, -0.002), name="top plate")
    sim = Simulation(np.full(len(x), r), x, walls=[walls.plane((0, 0, 0), (0, 0, 1)), plate],
                     settings=SolverSettings(time_step=2e-4, tolerance=1e-4, max_sweeps=2000),
                     domain=((-0.01,) * 3, (0.04, 0.04, 0.04)))
    assert sim.create_bonds(1e-6) > 50
    sim.step(5)
    return sim


def test_a_loose_tolerance_leaves_the_step_off_its_solution(benchmark_script, precision):
    if precision == "f32":
        pytest.skip("its reference is solved to 1e-12, which f32's rounding does not reach")
    step_error = benchmark_script("step_error").step_error
    sim = sheared_pile()
    state, t, k = sim.state_dict(), sim.time, sim.step_index
    rows = {}
    for tol in (1e-2, 1e-6, 1e-12):
        sim.load_state_dict(state)
        sim.time, sim.step_index = t, k
        rows[tol] = step_error(sim, 2e-4, tol, settle_steps=3, reference_tolerance=1e-12,
                               reference_sweeps=20000, max_sweeps=20000)
    loose, tight, same = rows[1e-2], rows[1e-6], rows[1e-12]
    # the reference converged, and the plate carries a force along x
    assert loose["reference_residual"] <= 1e-12 and loose["reference_sweeps"] < 20000
    assert abs(loose["wall_force_N"]) > 0
    # stopped at 1e-2 the step is off; at 1e-6 much closer; at the reference's own tolerance
    # the two solves are the same solve, bit for bit (the state and clock were restored)
    assert loose["sweeps"] < loose["reference_sweeps"]
    assert loose["impulse_error"] > 10 * tight["impulse_error"] > 0
    assert loose["bond_impulse_error"] > tight["bond_impulse_error"]
    # per grain (mm/s): the loose step's grains are off by more, the tails above the medians
    assert loose["velocity_error_median_mm_s"] > tight["velocity_error_median_mm_s"] > 0
    for row in (loose, tight):
        assert row["velocity_error_p99_mm_s"] >= row["velocity_error_median_mm_s"]
    assert loose["reference_speed_median_mm_s"] > 0
    # the energy norm of the velocity error against the step's own, the mass-weighted RMS and
    # the most loaded bonds' forces: all larger for the loose step
    for key in ("energy_error_ratio", "velocity_error_mass_rms_mm_s",
                "loaded_bonds_error_median", "loaded_bonds_error_max"):
        assert loose[key] > tight[key] > 0, key
    assert loose["loaded_bonds_error_max"] >= loose["loaded_bonds_error_median"]
    for key in ("impulse_error", "bond_impulse_error", "velocity_error", "wall_force_error",
                "velocity_error_median_mm_s", "velocity_error_p99_mm_s", "energy_error_ratio",
                "velocity_error_mass_rms_mm_s", "loaded_bonds_error_median",
                "loaded_bonds_error_max"):
        assert same[key] == 0.0, key
    assert same["sweeps"] == same["reference_sweeps"]
    # several tolerances from one settled state and one reference: the row of the tolerance
    # it settled at is the single tolerance's row, number for number
    sim.load_state_dict(state)
    sim.time, sim.step_index = t, k
    script = benchmark_script("step_error")
    both = script.step_errors(sim, 2e-4, [1e-2, 1e-6], settle_steps=3, reference_tolerance=1e-12,
                              reference_sweeps=20000, max_sweeps=20000)
    assert [row["tolerance"] for row in both] == [1e-2, 1e-6]
    assert both[0] == loose
    assert both[1]["impulse_error"] < both[0]["impulse_error"]
    sim.close()


def test_main_reads_a_checkpoint_and_its_scenario(benchmark_script, tmp_path, capsys, backend):
    """The command line: a run's checkpoint and scenario, one JSON row per time step."""
    if backend != ("cpu", "f64"):
        pytest.skip("the script runs in f64")
    from tcd import io, runner
    from tcd.config import parse_scenario
    script = benchmark_script("step_error")
    text = ('name = "pile"\nseeds = [1]\n[solver]\ntime_step = 2e-4\ntolerance = 1e-4\n'
            '[[stage]]\nkind = "shear"\nsample = "unused.h5"\n')
    scn_path = tmp_path / "pile.toml"
    scn_path.write_text(text)
    scn = parse_scenario(text, str(scn_path), resolve_samples=False)
    sim = sheared_pile()
    io.save_checkpoint(tmp_path / "checkpoint.h5", sim.state_dict(), runner.simulation_meta(sim))
    again = runner.restore_simulation(scn, *io.load_checkpoint(tmp_path / "checkpoint.h5"))
    assert np.array_equal(again.positions(), sim.positions())
    again.close()
    sim.close()
    rows = script.main([str(tmp_path / "checkpoint.h5"), str(scn_path), "--time-steps",
                        "2e-4,1e-4", "--tolerance", "1e-2", "--settle-steps", "2",
                        "--reference-sweeps", "20000", "--json"])
    assert [row["time_step"] for row in rows] == [2e-4, 1e-4]
    assert all(row["impulse_error"] > 0 for row in rows)
    assert capsys.readouterr().out.count('"impulse_error"') == 2
    # without --json, a Markdown table: its header and one row per time step
    script.main([str(tmp_path / "checkpoint.h5"), str(scn_path), "--time-steps", "2e-4",
                 "--tolerance", "1e-2", "--settle-steps", "2", "--reference-sweeps", "20000"])
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and "median / 99th percentile" in lines[0]
    assert all(line.count("|") == 13 for line in lines) and lines[2].startswith("| 0.0002 | 0.01 |")
    # two tolerances: a row for each, after one settling and one reference
    rows = script.main([str(tmp_path / "checkpoint.h5"), str(scn_path), "--time-steps", "2e-4",
                        "--tolerance", "1e-2,1e-6", "--settle-steps", "2",
                        "--reference-sweeps", "20000", "--json"])
    assert [row["tolerance"] for row in rows] == [1e-2, 1e-6]
    assert rows[0]["reference_sweeps"] == rows[1]["reference_sweeps"]
    assert rows[0]["impulse_error"] > rows[1]["impulse_error"]
    assert {row["convergence"] for row in rows} == {"impulse"}
    # the compared step stopped by LMGC90's Quad check instead: the same settling and reference
    args = [str(tmp_path / "checkpoint.h5"), str(scn_path), "--time-steps", "2e-4", "--tolerance",
            "1e-6", "--settle-steps", "2", "--reference-sweeps", "20000", "--json"]
    (impulse,), (quad,) = script.main(args), script.main(args + ["--convergence", "quad"])
    assert (impulse["convergence"], quad["convergence"]) == ("impulse", "quad")
    assert quad["reference_sweeps"] == impulse["reference_sweeps"]
    assert quad["reference_residual"] == impulse["reference_residual"]
    assert quad["sweeps"] != impulse["sweeps"]
