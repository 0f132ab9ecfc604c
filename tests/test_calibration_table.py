"""benchmarks/calibration_table.py reads run directories without running anything: a finished
run gives its settings, peak and raw stresses; an unfinished one is listed as running."""
import json

import pytest


@pytest.fixture(scope="module")
def table(benchmark_script):
    return benchmark_script("calibration_table")


def _run(tmp_path, name, finished):
    run = tmp_path / name
    (run / "sample_3").mkdir(parents=True)
    (run / "scenario.toml").write_text(
        'name = "x"\n[bond]\nyield_stress_MPa = 1.7\ngap_tolerance_mm = 0.5\n'
        '[solver]\ntolerance = 1e-4\n[[stage]]\nkind = "shear"\nwall_friction = 0.25\ntolerance = 1e-5\n')
    d = [0.0005 * k for k in range(0, 6)]                 # m: 0 to 2.5 mm
    tau = [0.4e6 * k for k in range(0, 6)]                # Pa: 0.4 MPa per 0.5 mm
    lines = ["time [s],displacement [m],shear_stress [Pa]"]
    lines += [f"{0.1 * k},{d[k]!r},{tau[k]!r}" for k in range(6)]
    (run / "sample_3" / "shear_series.csv").write_text("\n".join(lines) + "\n")
    if finished:
        sh = {"tau_peak_MPa": 2.0, "d_peak_mm": 2.5, "bonds_broken": 12, "bonds_total": 100,
              "broken_near_plane_fraction": 0.75}
        (run / "summary.json").write_text(json.dumps({"samples": [{"seed": 3, "stages": {"0:shear": sh}}]}))
    return run


def test_finished_run_row(table, tmp_path):
    rows = table.rows_of(_run(tmp_path, "a", True), [0.5, 1.0, 2.5, 3.0])
    assert rows == [["a", "3", "1.7", "0.25", "0.5", "1e-05", "2.000 at 2.50",
                     "0.400", "0.800", "2.000", "", "12 / 100", "0.75", "done"]]


def test_unfinished_run_is_listed_as_running(table, tmp_path):
    rows = table.rows_of(_run(tmp_path, "b", False), [1.0])
    assert rows[0][7] == "0.800" and rows[0][-1] == "running (2.50 mm)" and rows[0][6] == ""


def test_not_a_run_directory_is_named(table, tmp_path, capsys):
    with pytest.raises(SystemExit):
        table.main([str(tmp_path)])
    assert "no scenario.toml" in capsys.readouterr().err


def test_finished_sample_of_a_running_study_is_read_from_its_own_summary(table, tmp_path):
    run = _run(tmp_path, "c", False)
    sh = {"tau_peak_MPa": 0.9, "d_peak_mm": 2.25, "bonds_broken": 7, "bonds_total": 70,
          "broken_near_plane_fraction": 0.5}
    (run / "sample_3" / "summary.json").write_text(json.dumps({"seed": 3, "stages": {"0:shear": sh}}))
    row = table.rows_of(run, [1.0])[0]
    assert row[6] == "0.900 at 2.25" and row[-3:] == ["7 / 70", "0.50", "done"]
