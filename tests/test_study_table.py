"""benchmarks/study_table.py lists a finished study from its summary.json: rows per sample,
then mean and std, the paper, the experiments and the relative errors as the runner wrote them."""
import json

import pytest


@pytest.fixture(scope="module")
def table(benchmark_script):
    return benchmark_script("study_table")


def _sample(seed, tau, d):
    return {"seed": seed, "stages": {"0:shear": {
        "particles": 5857, "tau_peak_MPa": tau, "d_peak_mm": d, "residual_MPa": 0.7,
        "bonds_broken": 30, "bonds_broken_tension": 10, "bonds_broken_shear": 20, "bonds_total": 100,
        "broken_near_plane_fraction": 0.7, "bonds_near_plane_fraction": 0.3,
        "upper_mean_dx_over_ring": 0.84, "lower_mean_dx_over_ring": 0.15,
        "kinetic_over_work_max": 2.4e-4, "wall_time_s": 1500.4}}}


def _write_summary(run_dir, samples, tau, d, tau_std, d_std):
    """A run's summary.json as the runner writes it: the samples, their mean (tau, d) and std,
    the paper's numbers and the relative errors."""
    (run_dir / "summary.json").write_text(json.dumps({
        "samples": samples,
        "mean": {"tau_peak_MPa": tau, "d_peak_mm": d, "residual_MPa": 0.7},
        "std": {"tau_peak_MPa": tau_std, "d_peak_mm": d_std, "residual_MPa": 0.0},
        "experiment": {"tau_peak_MPa": 0.898, "d_peak_mm": 2.37},
        "paper_simulation": {"tau_peak_MPa": 0.837, "d_peak_mm": 2.2},
        "relative_error": {"tau_peak": tau / 0.898 - 1, "d_peak": d / 2.37 - 1}}))


def test_rows_and_summary_lines(table, tmp_path, capsys):
    _write_summary(tmp_path, [_sample(1, 0.9, 2.3), _sample(2, 1.0, 2.1)], 0.95, 2.2, 0.05, 0.1)
    assert table.main([str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 + 2 + 4
    assert lines[2].startswith("| 1 | 5857 | 0.900 | 2.30 | 0.700 | 30 (10 + 20) / 100 | 0.70 (0.30) | 0.84 / 0.15 | 2.4e-04 | 1500 |")
    assert "| mean ± std |  | 0.950 ± 0.050 | 2.20 ± 0.10 |" in lines[4]
    assert "+5.8 %" in lines[7] and "-7.2 %" in lines[7]


def test_a_peak_at_the_end_of_a_rising_curve_is_marked(table, tmp_path, capsys):
    rising = _sample(2, 1.0, 2.5)
    rising["stages"]["0:shear"]["peak_at_end"] = True
    falling = _sample(1, 0.9, 2.3)
    falling["stages"]["0:shear"]["peak_at_end"] = False
    _write_summary(tmp_path, [falling, rising], 0.95, 2.4, 0.05, 0.1)
    assert table.main([str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].startswith("| 1 | 5857 | 0.900 | 2.30 | 0.700 |")
    assert lines[3].startswith("| 2 | 5857 | 1.000 | 2.50 (end) | 0.700 |")


def test_one_sample_has_no_spread(table, tmp_path, capsys):
    _write_summary(tmp_path, [_sample(1, 0.9, 2.3)], 0.9, 2.3, 0.0, 0.0)
    assert table.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "±" not in out and "mean" not in out
    assert out.splitlines()[-1].startswith("| vs experiments |  | +0.2 % | -3.0 % |")


def test_unfinished_run_is_refused(table, tmp_path, capsys):
    with pytest.raises(SystemExit):
        table.main([str(tmp_path)])
    assert "no summary.json" in capsys.readouterr().err


def test_another_test_than_the_paper_s_gets_no_comparison_but_a_note(table, tmp_path, capsys):
    _write_summary(tmp_path, [_sample(1, 0.9, 2.3)], 0.9, 2.3, 0.0, 0.0)
    summary = json.loads((tmp_path / "summary.json").read_text())
    summary.update(paper_test=False, experiment=None, paper_simulation=None, relative_error=None,
                   paper_test_differences=["a shear at 600 mm/min (the paper's: 50)"])
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    assert table.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "experiments (" not in out and "LMGC90" not in out and " %" not in out
    assert "| 1 | 5857 | 0.900 | 2.30 |" in out
    assert out.rstrip().endswith("this test is not its Leutner test (a shear at 600 mm/min "
                                 "(the paper's: 50)).")
