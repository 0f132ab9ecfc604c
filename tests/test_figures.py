"""tcd.figures: smoothing, peak detection, Table 2 and the headless outputs of a run directory."""
import json
import math
import os
import sys
import types

import imageio.v3 as iio
import numpy as np
import pytest

from tcd import figures, io
from tcd.figures import (FigureWarning, load_sample, make_figures, merge_summaries, peak_of,
                         render_frames, smooth, summary_from_samples, table2_rows)

pytestmark = [pytest.mark.filterwarnings("ignore::DeprecationWarning"),
              pytest.mark.filterwarnings("ignore:.*summary.json missing:UserWarning"),
              pytest.mark.filterwarnings("ignore:.*no sample has a states.h5:UserWarning")]


# --- smooth ----------------------------------------------------------------------------------
def test_smooth_of_constant_is_the_constant():
    x = np.sort(np.random.default_rng(0).uniform(0.0, 1.0, 200))
    np.testing.assert_allclose(smooth(np.full(200, 3.25), x, 0.1), 3.25, rtol=1e-14)


def test_smooth_reduces_variance_of_noise():
    rng = np.random.default_rng(1)
    x = np.linspace(0.0, 1.0, 2001)
    y = rng.normal(0.0, 1.0, x.size)
    s = smooth(y, x, 0.05)  # about 100 points per window -> variance / 100
    assert np.var(s) < 0.05 * np.var(y)


def test_smooth_window_is_in_x_units_on_nonuniform_x():
    # dense on the left, sparse on the right: the window counts x distance, not points
    x = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 1.0, 2.0, 3.0])
    y = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0])
    s = smooth(y, x, 0.5)  # |x_j - x_i| <= 0.25
    assert s[2] == pytest.approx(np.mean([2.0, 3.0, 4.0]))       # 0.1, 0.2, 0.3
    assert s[0] == pytest.approx(np.mean([1.0, 2.0, 3.0]))       # edge: 0, 0.1, 0.2 only
    assert s[5] == pytest.approx(6.0)                             # isolated point
    s_wide = smooth(y, x, 2.2)  # |dx| <= 1.1
    assert s_wide[6] == pytest.approx(np.mean([6.0, 7.0, 8.0]))
    # order of the samples does not matter
    perm = np.random.default_rng(2).permutation(x.size)
    np.testing.assert_allclose(smooth(y[perm], x[perm], 0.5), s[perm])


# --- peak_of ---------------------------------------------------------------------------------
def test_peak_of_finds_the_peak_of_a_noisy_bump():
    rng = np.random.default_rng(3)
    d = np.linspace(0.0, 2.5e-3, 15000)
    true_d, true_tau = 2.2e-3, 0.84e6
    tau = true_tau * np.exp(-0.5 * ((d - true_d) / 0.4e-3) ** 2)
    noisy = tau + rng.normal(0.0, 0.05e6, d.size)
    noisy[6000] += 0.6e6                            # one-step spike at 1 mm: not the peak
    window = 5e-5
    tau_peak, d_peak, index = peak_of(d, noisy, window)
    assert abs(d_peak - true_d) < 2 * window
    assert tau_peak == pytest.approx(true_tau, rel=0.01)
    assert d[index] == d_peak
    assert tau_peak == pytest.approx(smooth(noisy, d, window)[index])
    # raw noise would overshoot: the smoothed peak is what is reported
    assert noisy.max() > true_tau + 0.1e6


def test_peak_of_monotonic_curve_is_the_last_point():
    d = np.linspace(0.0, 1.0, 500) ** 1.5          # non-uniform, increasing
    tau = 1.0 - np.exp(-3.0 * d)                    # concave, increasing
    tau_peak, d_peak, index = peak_of(d, tau, 0.05)
    assert index == d.size - 1
    assert d_peak == d[-1]
    assert tau_peak <= tau[-1]
    # a curve that saturates exactly: equal smoothed maxima, the last one is reported
    x = np.linspace(0.0, 1.0, 101)
    assert peak_of(x, np.minimum(x, 0.5), 0.1)[2] == 100


def test_a_peak_within_half_a_window_of_the_end_is_the_end_of_a_rising_curve():
    from tcd.observables import peak_at_end
    d = np.linspace(0.0, 2.5e-3, 2501)
    window = 1e-4
    rising = 1.0 - np.exp(-d / 1e-3)
    bump = np.exp(-0.5 * ((d - 2.0e-3) / 2e-4) ** 2)
    assert peak_at_end(d, peak_of(d, rising, window)[1], window)
    assert not peak_at_end(d, peak_of(d, bump, window)[1], window)
    assert peak_at_end(d, 2.5e-3 - 0.49 * window, window)
    assert not peak_at_end(d, 2.5e-3 - 0.51 * window, window)
    # the last point is the largest displacement, whatever the order and NaN
    assert peak_at_end(np.r_[d[::-1], np.nan], 2.46e-3, window)
    assert not peak_at_end(np.array([np.nan]), 0.0, window)


# --- Table 2 ---------------------------------------------------------------------------------
def _summary(taus=(0.80, 0.86, 0.83), ds=(2.1, 2.3, 2.2)):
    samples = [{"seed": s, "tau_peak_MPa": t, "d_peak_mm": d, "bonds_total": 2000}
               for s, t, d in zip((11, 12, 13), taus, ds)]
    return {"scenario": "synthetic", "samples": samples,
            "mean": {"tau_peak_MPa": float(np.mean(taus)), "d_peak_mm": float(np.mean(ds)),
                     "residual_MPa": 0.3},
            "std": {"tau_peak_MPa": float(np.std(taus, ddof=1)),
                    "d_peak_mm": float(np.std(ds, ddof=1)), "residual_MPa": 0.01},
            "experiment": {"tau_peak_MPa": 0.898, "d_peak_mm": 2.37},
            "paper_simulation": {"tau_peak_MPa": 0.837, "d_peak_mm": 2.2}}


def test_table2_rows_values_and_relative_errors():
    rows = table2_rows(_summary())
    assert [r["label"] for r in rows][:2] == ["experiments", "paper simulations (LMGC90)"]
    assert "3 samples" in rows[2]["label"]
    exp, paper, run = rows
    assert (exp["tau_MPa"], exp["d_mm"]) == (0.898, 2.37)
    assert math.isnan(exp["tau_rel_error"]) and math.isnan(exp["d_rel_error"])
    assert paper["tau_rel_error"] == pytest.approx((0.837 - 0.898) / 0.898)
    assert paper["d_rel_error"] == pytest.approx((2.2 - 2.37) / 2.37)
    assert run["tau_MPa"] == pytest.approx(0.83)
    assert run["d_mm"] == pytest.approx(2.2)
    assert run["tau_std_MPa"] == pytest.approx(0.03)
    assert run["n_samples"] == 3
    assert run["tau_rel_error"] == pytest.approx((0.83 - 0.898) / 0.898)
    assert run["d_rel_error"] == pytest.approx((2.2 - 2.37) / 2.37)


def test_table2_rows_fall_back_to_samples_when_mean_is_missing():
    summary = _summary(taus=(0.9, 1.0), ds=(2.0, 2.4))
    del summary["mean"], summary["std"]
    run = table2_rows(summary)[2]
    assert run["tau_MPa"] == pytest.approx(0.95)
    assert run["d_mm"] == pytest.approx(2.2)
    assert run["d_std_mm"] == pytest.approx(0.2)
    # three samples with one high: the mean (not the median) and the population std
    summary = {"samples": [{"tau_peak_MPa": 0.8, "d_peak_mm": 2.0},
                           {"tau_peak_MPa": 0.9, "d_peak_mm": 2.1},
                           {"tau_peak_MPa": 1.3, "d_peak_mm": 2.9}]}
    run = table2_rows(summary)[2]
    assert run["tau_MPa"] == pytest.approx(1.0) and run["d_mm"] == pytest.approx(7.0 / 3.0)
    assert run["tau_std_MPa"] == pytest.approx(math.sqrt((0.04 + 0.01 + 0.09) / 3))
    assert run["tau_rel_error"] == pytest.approx(1.0 / 0.898 - 1.0)


# --- run directories -------------------------------------------------------------------------
def _write_sample(run_dir, seed, tau_peak, d_peak, *, attrs=True, n=3000):
    rng = np.random.default_rng(seed)
    d = np.linspace(0.0, 2.5e-3, n)
    rise = tau_peak * np.sin(0.5 * np.pi * np.clip(d / d_peak, 0.0, 1.0)) ** 1.5
    residual = 0.35e6 + (tau_peak - 0.35e6) * np.exp(-(d - d_peak) / 1e-4)
    tau = np.where(d <= d_peak, rise, residual) + rng.normal(0.0, 0.02e6, n)
    total = 2000
    tension = np.round(800 * np.clip(d / 2.5e-3, 0, 1) ** 3).astype(np.int64)
    shear = np.round(300 * np.clip((d - 1.5e-3) / 1e-3, 0, 1) ** 2).astype(np.int64)
    series = {"time": d / (50e-3 / 60.0), "step": np.arange(n), "displacement": d,
              "shear_force": tau * np.pi * 0.075 ** 2, "shear_stress": tau,
              "bonds_intact": total - tension - shear, "bonds_broken_tension": tension,
              "bonds_broken_shear": shear, "sweeps": np.full(n, 50), "residual": np.full(n, 1e-6),
              "contacts": np.full(n, 5000), "kinetic_energy": np.full(n, 1e-6)}
    folder = run_dir / f"sample_{seed}"
    folder.mkdir(parents=True)
    root = {"tau_peak": tau_peak, "d_peak": d_peak, "smoothing_window": 5e-5} if attrs else {}
    io.write_series(folder / "shear_series.h5", series, attrs=root,
                    units={"time": "s", "displacement": "m", "shear_stress": "Pa"})


def test_make_figures_writes_the_paper_outputs(tmp_path):
    run = tmp_path / "run"
    peaks = {11: (0.80e6, 2.1e-3), 12: (0.86e6, 2.3e-3), 13: (0.83e6, 2.2e-3)}
    for seed, (t, d) in peaks.items():
        _write_sample(run, seed, t, d, attrs=(seed != 13))   # seed 13: peaks computed here
    (run / "summary.json").write_text(json.dumps(_summary()))
    with pytest.warns(FigureWarning, match="fig2.*fig3.*skipped"):
        written = make_figures(run)
    names = sorted(p.name for p in written)
    assert names == sorted(["fig4_stress_displacement.png", "fig4_stress_displacement.pdf",
                            "table2.md", "table2.csv", "table2.png", "bonds_broken.png"])
    for path in written:
        assert path.parent == run / "figures" and path.stat().st_size > 0
    assert not list((run / "figures").glob(".*.tmp"))
    for name in ("fig4_stress_displacement.png", "table2.png", "bonds_broken.png"):
        image = iio.imread(run / "figures" / name)
        assert image.ndim == 3 and image.shape[0] >= 250 and image.shape[1] >= 600
        assert image[..., :3].std() > 5          # not blank
    md = (run / "figures" / "table2.md").read_text()
    for text in ("0.898", "2.37", "0.837", "2.20", "0.830 ± 0.030", "-7.6 %", "-7.2 %"):
        assert text in md
    assert "still rose" not in md                  # every sample peaked before its end
    csv_lines = (run / "figures" / "table2.csv").read_text().splitlines()
    assert len(csv_lines) == 4 and csv_lines[0].startswith("label,tau_MPa")
    # the same figures are the same bytes: the PDF carried its creation date (session 48)
    pdf = (run / "figures" / "fig4_stress_displacement.pdf").read_bytes()
    assert pdf.startswith(b"%PDF") and b"/CreationDate" not in pdf


def test_make_figures_skips_samples_without_series(tmp_path):
    run = tmp_path / "run"
    _write_sample(run, 5, 0.85e6, 2.2e-3)
    (run / "sample_6").mkdir()                   # still running: no series yet
    out = tmp_path / "out"
    with pytest.warns(FigureWarning, match="sample 6 skipped") as caught:
        written = make_figures(run, out)        # no summary.json: table from the series
    # the file and what is missing, not Python's "[Errno 2] ...: 'PATH'" (before session 72)
    assert (f"sample 6 skipped: {run / 'sample_6' / 'shear_series.h5'}: no such tcd series "
            "file") in [str(w.message) for w in caught]
    assert (out / "fig4_stress_displacement.png") in written
    md = (out / "table2.md").read_text()
    assert "0.850" in md and "2.20" in md and "one sample" in md and "±" not in md
    # a reader of the table alone learns that a sample is missing from its mean
    assert ("Left out of this table and the figures: sample 6 (no series file yet: stopped or "
            "still running). The means are over the other 1 sample;") in md, md
    # a sample with an unreadable series, beside one still running, and two counted
    _write_sample(run, 4, 0.80e6, 2.1e-3)
    (run / "sample_7").mkdir()
    (run / "sample_7" / "shear_series.h5").write_bytes(b"not HDF5")
    with pytest.warns(FigureWarning, match="sample 6 skipped"), \
            pytest.warns(FigureWarning, match="sample 7 skipped"):
        make_figures(run, out, render=False)
    md = (out / "table2.md").read_text()
    assert ("Left out of this table and the figures: sample 6 (no series file yet: stopped or "
            "still running); sample 7 (its series unreadable). The means are over the other 2 "
            "samples;") in md, md
    # nothing left out: no such sentence
    (run / "sample_6").rmdir()
    for f in (run / "sample_7").iterdir():
        f.unlink()
    (run / "sample_7").rmdir()
    make_figures(run, out, render=False)
    assert "Left out" not in (out / "table2.md").read_text()


@pytest.mark.parametrize("text, why", [("[]", "not a JSON object"),
                                       ('{"samples": "x"}', "'samples' is not a list"),
                                       ('{"mean": [1, 2]}', "'mean' is not an object")])
def test_a_summary_of_the_wrong_shape_is_set_aside_with_a_warning(tmp_path, text, why):
    """Valid JSON that is not a run's summary (a list; samples as a string) stopped `tcd
    figures` with an AttributeError (session 42 audit); now it is read as an unreadable one."""
    run = tmp_path / "run"
    _write_sample(run, 5, 0.85e6, 2.2e-3)
    (run / "summary.json").write_text(text)
    out = tmp_path / "out"
    with pytest.warns(FigureWarning, match="summary.json unreadable: Table 2 from the series peaks"), \
            pytest.warns(FigureWarning, match=f"summary.json: unreadable .*{why}"):
        written = make_figures(run, out)
    assert (out / "fig4_stress_displacement.png") in written
    assert "0.850" in (out / "table2.md").read_text()


def test_make_figures_without_usable_series_names_the_directory(tmp_path):
    run = tmp_path / "empty_run"
    (run / "sample_1").mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps(_summary()))
    with pytest.warns(FigureWarning), pytest.raises(ValueError, match="empty_run.*no usable"):
        make_figures(run)
    assert not (run / "figures").exists() or not any((run / "figures").iterdir())


# --- a study split across runs (tcd run --seeds) ------------------------------------------------
_SCENARIO = 'name = "synthetic"\nseeds = [11, 12, 13]\n[bond]\nyield_stress_MPa = 1.6\n'


def _split_study(tmp_path, second_seeds=(13,), scenario=_SCENARIO, arch="cpu"):
    """The three samples of make_figures' test as two runs: seeds 11, 12, then `second_seeds`."""
    peaks = {11: (0.80e6, 2.1e-3), 12: (0.86e6, 2.3e-3), 13: (0.83e6, 2.2e-3)}
    runs = []
    for name, seeds, text, backend in (("a", (11, 12), _SCENARIO, "cpu"),
                                       ("b", second_seeds, scenario, arch)):
        run = tmp_path / name
        for seed in seeds:
            _write_sample(run, seed, *peaks[seed])
        summary = _summary()
        summary["samples"] = [s for s in summary["samples"] if s["seed"] in seeds]
        summary["mean"] = {"tau_peak_MPa": 9.9}     # a part's own mean: not the study's
        (run / "summary.json").write_text(json.dumps(summary))
        (run / "scenario.toml").write_text(text.replace("[11, 12, 13]", str(list(seeds))))
        (run / "run.json").write_text(json.dumps({"arch": backend, "precision": "f64"}))
        runs.append(run)
    return runs


def test_figures_of_a_study_split_across_runs(tmp_path):
    # another name, description and output (the quick scenario and the whole study) are fine
    renamed = _SCENARIO.replace('"synthetic"', '"synthetic_quick"\ndescription = "one seed"')
    runs = _split_study(tmp_path, scenario=renamed + "[output]\nsnapshot_every = 0.5\n")
    out = tmp_path / "study"
    with pytest.warns(FigureWarning, match="fig2.*fig3.*skipped"):
        written = make_figures(runs, out)
    assert {p.name for p in written} >= {"fig4_stress_displacement.png", "table2.md",
                                         "study_summary.json", "bonds_broken.png"}
    study = json.loads((out / "study_summary.json").read_text())
    assert [s["seed"] for s in study["samples"]] == [11, 12, 13]
    assert study["merged_from"] == [str(r) for r in runs]
    assert study["mean"]["tau_peak_MPa"] == pytest.approx(0.83)
    assert study["std"]["d_peak_mm"] == pytest.approx(np.std([2.1, 2.3, 2.2]))
    assert study["relative_error"]["d_peak"] == pytest.approx(2.2 / 2.37 - 1.0)
    md = (out / "table2.md").read_text()
    assert "3 samples" in md and "0.830 ±" in md and "-7.6 %" in md
    assert not (runs[0] / "figures").exists()       # the parts are left as they are


def test_a_seed_unfinished_in_one_part_and_finished_in_another_is_not_skipped(tmp_path):
    """Part a was interrupted as it began seed 13 (no summary.json, an empty sample_13), which
    part b then ran: the merge takes b's and says nothing of a's (session 50 saw "sample 4
    skipped" for a study whose five samples were all drawn); a seed missing from every part is
    still reported."""
    import warnings
    runs = _split_study(tmp_path)
    (runs[0] / "summary.json").unlink()
    (runs[0] / "sample_13").mkdir()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary, samples = figures.load_runs(runs)
    assert [str(s.seed) for s in samples] == ["11", "12", "13"]
    assert [smp["seed"] for smp in summary["samples"]] == [11, 12, 13]     # numbers, as written
    assert not [w for w in caught if "sample 13" in str(w.message)], [str(w.message) for w in caught]
    (runs[0] / "sample_14").mkdir()
    with pytest.warns(FigureWarning, match="sample 14 skipped"):
        figures.load_runs(runs)


def test_figures_of_a_split_study_refuse_a_seed_twice_and_another_scenario(tmp_path):
    runs = _split_study(tmp_path / "twice", second_seeds=(12, 13))
    with pytest.raises(ValueError, match=r"sample 12 is in both .*a and .*b"):
        make_figures(runs, tmp_path / "out1")
    changed = _SCENARIO.replace("1.6", "1.9")
    runs = _split_study(tmp_path / "other", scenario=changed)
    with pytest.raises(ValueError, match=r"bond.yield_stress_MPa: 1.6 -> 1.9"):
        make_figures(runs, tmp_path / "out2")
    assert not (tmp_path / "out1").exists() and not (tmp_path / "out2").exists()
    with pytest.raises(ValueError, match="--out"):
        make_figures(runs)


def test_parts_of_a_study_are_compared_by_their_checked_settings(tmp_path):
    """A part whose scenario wrote out a default value (`density = 2600.0`) was refused as
    "another scenario", unlike --resume, which compares the checked settings; the sample
    files need not exist any more to compare."""
    valid = ('name = "synthetic"\nseeds = [11, 12, 13]\n[bond]\nyield_stress_MPa = 1.6\n'
             '[[stage]]\nkind = "shear"\nsample = "gone/s_{seed}.h5"\n')
    (tmp_path / "same").mkdir()
    runs = _split_study(tmp_path / "same", scenario=valid.replace(
        "[bond]", "[material]\ndensity = 2600.0\n[bond]"))
    (runs[0] / "scenario.toml").write_text(valid.replace("[11, 12, 13]", "[11, 12]"))
    make_figures(runs, tmp_path / "out", render=False)
    assert (tmp_path / "out" / "table2.md").is_file()
    (tmp_path / "other").mkdir()
    runs = _split_study(tmp_path / "other", scenario=valid.replace(
        "[bond]", "[material]\ndensity = 2650.0\n[bond]"))
    (runs[0] / "scenario.toml").write_text(valid.replace("[11, 12, 13]", "[11, 12]"))
    with pytest.raises(ValueError, match=r"material.density: 2600.0 -> 2650.0"):
        make_figures(runs, tmp_path / "out2", render=False)


def test_figures_of_a_split_study_warn_about_different_backends(tmp_path):
    runs = _split_study(tmp_path, arch="gpu")
    with pytest.warns(FigureWarning, match="cpu/f64 and .* on gpu/f64"):
        make_figures(runs, tmp_path / "out", render=False)


def test_render_frames_choose_prepared_and_peak_frames():
    stages = [(0.0, "prepare"), (1.0, "prepare"), (2.0, "shear"), (2.5, "shear"),
              (3.0, "shear"), (4.0, "shear")]
    assert render_frames(stages, 2.9) == (1, [3, 4])      # early (10 % of the way), peak
    assert render_frames(stages, math.nan) == (1, [3, 5])
    assert render_frames(stages, 2.4) == (1, [2, 3])      # early would be the peak's frame
    # the frames of the first steps (the bonded sample settling) are not "early"
    steps = [(0.0, "prepare"), (3.44, "shear"), (3.4402, "shear"), (3.5, "shear"),
             (3.75, "shear"), (4.0, "shear"), (6.25, "shear"), (6.44, "shear")]
    assert render_frames(steps, 6.2) == (0, [4, 6])
    assert render_frames([(0.0, "pour"), (1.0, "pour")], 1.0) == (0, [])


def _write_states(path, stages):
    x = np.array([[0.0, 0.0, 0.01], [0.0, 0.0, 0.03]])
    for k, (time, stage) in enumerate(stages):
        io.append_frame(path, {"particles/x": x, "particles/radius": np.full(2, 0.01),
                               "particles/v": np.zeros((2, 3))}, time=time, step=k, stage=stage)


def test_make_figures_renders_fig2_and_fig3_at_the_right_frames(tmp_path, monkeypatch):
    from tcd import render
    run = tmp_path / "run"
    _write_sample(run, 7, 0.85e6, 2.2e-3)
    peak_time = 2.2e-3 / (50e-3 / 60.0)            # 2.64 s at 50 mm/min
    _write_states(run / "sample_7" / "states.h5",
                  [(0.0, "prepare"), (0.4, "prepare"), (0.5, "shear"), (1.5, "shear"),
                   (peak_time + 0.1, "shear"), (3.0, "shear")])
    calls = {}

    def fake(name):
        def draw(path, out, frame=None, frames=None, velocity=None):
            calls[name] = (path, frame if frames is None else list(frames))
            calls[name + " velocity"] = velocity
            iio.imwrite(out, np.zeros((8, 8, 3), np.uint8))
        return draw

    monkeypatch.setattr(render, "figure_sample", fake("fig2"))
    monkeypatch.setattr(render, "figure_velocity", fake("fig3"))
    written = make_figures(run)
    assert calls["fig2"] == (run / "sample_7" / "states.h5", 1)   # last "prepare" frame
    assert calls["fig3"][1] == [3, 4]                              # early shear, nearest peak
    assert calls["fig3 velocity"] == "mean"                        # the paper's average velocity
    make_figures(run, tmp_path / "instant", velocity="instant")
    assert calls["fig3 velocity"] == "instant"
    with pytest.raises(ValueError, match="velocity 'average': expected one of mean, instant"):
        make_figures(run, tmp_path / "bad", velocity="average")
    assert {"fig2_sample.png", "fig3_velocity.png"} <= {p.name for p in written}


def test_a_failing_render_is_skipped_with_a_warning(tmp_path, monkeypatch):
    from tcd import render
    run = tmp_path / "run"
    _write_sample(run, 7, 0.85e6, 2.2e-3)
    _write_states(run / "sample_7" / "states.h5", [(0.0, "prepare"), (1.0, "shear")])

    def broken(*args, **kwargs):
        raise RuntimeError("no renderer today")

    monkeypatch.setattr(render, "figure_sample", broken)
    monkeypatch.setattr(render, "figure_velocity", broken)
    with pytest.warns(FigureWarning) as record:
        written = make_figures(run)
    messages = " | ".join(str(w.message) for w in record)
    assert "fig2_sample.png skipped: RuntimeError: no renderer today" in messages
    assert "fig3_velocity.png skipped: RuntimeError: no renderer today" in messages
    names = {p.name for p in written}
    assert "fig2_sample.png" not in names and "fig3_velocity.png" not in names
    assert {"fig4_stress_displacement.png", "table2.png", "bonds_broken.png"} <= names


# --- session 43's mutation audit: the study's statistics and the default smoothing ------------
def test_summary_from_samples_is_the_mean_and_population_std():
    samples = [types.SimpleNamespace(seed=str(k), tau_peak=t * 1e6, d_peak=d * 1e-3)
               for k, (t, d) in enumerate([(0.8, 2.0), (0.9, 2.1), (1.3, 2.9)])]
    out = summary_from_samples(samples)
    assert out["mean"]["tau_peak_MPa"] == pytest.approx(1.0)
    assert out["std"]["tau_peak_MPa"] == pytest.approx(math.sqrt((0.04 + 0.01 + 0.09) / 3))


def test_series_without_a_window_is_smoothed_over_0_1_mm(tmp_path):
    """A series file without `smoothing_window` (nor the runner's peak): the default window is
    0.1 mm of displacement (shear.smoothing_window_mm), so a triangle peaking at 1.2 mm of a
    2.5 mm travel peaks there, not at the end of a curve averaged flat."""
    d = np.linspace(0.0, 2.5e-3, 2526)      # the half window is 50.5 intervals: no edge ties
    tau = 1e6 * np.maximum(0.0, 1.0 - np.abs(d - 1.2e-3) / 1.2e-3) + 1e5
    folder = tmp_path / "sample_1"
    folder.mkdir()
    io.write_series(folder / "shear_series.h5", {"time": d, "displacement": d,
                                                 "shear_stress": tau})
    s = load_sample("1", folder)
    assert s.window == pytest.approx(1e-4)
    assert s.d_peak == pytest.approx(1.2e-3, abs=1e-6)
    linear = (d > 0.1e-3) & (d < 1.1e-3)    # a linear stretch: the average is exact
    np.testing.assert_allclose(s.smoothed[linear], tau[linear], rtol=1e-9)


@pytest.mark.parametrize("value, shown", [(np.array([b"x"] * 3000), "dtype |S1"),
                                          (np.zeros(1), "shape (1,)"),
                                          (np.zeros((3000, 2)), "shape (3000, 2)")])
def test_a_series_of_the_wrong_shape_or_type_skips_its_sample_naming_file_and_key(tmp_path, value,
                                                                                  shown):
    """A damaged shear_series.h5 (a series of strings, of one record, or of pairs) stopped `tcd
    figures` with NumPy's or Matplotlib's words ("could not convert string to float", "x and y
    must have same first dimension"), naming neither the file nor the series (session 47)."""
    import h5py
    run = tmp_path / "run"
    _write_sample(run, 5, 0.85e6, 2.2e-3)
    _write_sample(run, 6, 0.80e6, 2.1e-3)
    damaged = run / "sample_6" / "shear_series.h5"
    with h5py.File(damaged, "a") as f:
        del f["bonds_broken_shear"]
        f["bonds_broken_shear"] = value
    out = tmp_path / "out"
    with pytest.warns(FigureWarning, match=f"sample 6 skipped: {damaged}: series "
                                           f"'bonds_broken_shear' has {shown.replace('(', '.').replace(')', '.')}"):
        written = make_figures(run, out)
    assert (out / "fig4_stress_displacement.png") in written


def test_fig4_of_a_short_test_is_drawn_over_its_own_range(tmp_path, monkeypatch):
    """Fig. 4's axis ended at the paper's 2.5 mm whatever the test: a 0.4 mm test was a stub
    in a corner, under the experiments' peak at 2.37 mm (the user audit of session 48). A test
    to 2.5 mm keeps the paper's frame and markers; one past it is drawn to its end."""
    from tcd import figures
    drawn = []
    monkeypatch.setattr(figures, "_save", lambda fig, path, written: drawn.append(fig))

    def curves(d_end):
        d = np.linspace(0.0, d_end, 200)
        tau = 2e5 * np.sin(np.pi * d / d_end)
        return figures.SampleCurves("1", tmp_path, d, d, tau, tau, 1e-5, 2e5, d_end / 2, 100, {})
    for d_end, xmax, markers in ((0.4e-3, 0.4, False), (2.5e-3, 2.5, True), (3.0e-3, 3.0, True)):
        drawn.clear()
        figures.figure_stress_displacement([curves(d_end)], tmp_path / "f.png", [], pdf=False)
        ax = drawn[0].axes[0]
        assert ax.get_xlim() == pytest.approx((0.0, xmax)), d_end
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert ("experiments (mean of 5 cores)" in labels) == markers, (d_end, labels)
        assert ax.get_ylim()[1] == pytest.approx(1.12 * (0.898 if markers else 0.2), rel=1e-3), d_end
    # the run's summary decides (a 2.5 mm test at 600 mm/min is not the paper's); a summary
    # without the flag (before session 49) falls back to the test's range
    for paper_test, markers in ((False, False), (True, True), (None, True)):
        drawn.clear()
        figures.figure_stress_displacement([curves(2.5e-3)], tmp_path / "f.png", [], pdf=False,
                                           paper_test=paper_test)
        labels = [t.get_text() for t in drawn[0].axes[0].get_legend().get_texts()]
        assert ("experiments (mean of 5 cores)" in labels) == markers, paper_test


def test_table2_of_another_test_than_the_paper_s_is_not_compared(tmp_path):
    """A run whose test is not the paper's Leutner test (its summary's `paper_test` false)
    gets its own row in Table 2, without the experiments and relative errors, and a line
    saying how its test differs."""
    run = tmp_path / "run"
    for seed, (t, d) in {11: (0.80e6, 2.1e-3), 12: (0.86e6, 2.3e-3)}.items():
        _write_sample(run, seed, t, d)
    differences = ["a shear at 600 mm/min (the paper's: 50)", "a mould of 30 mm (the paper's: 150 mm)"]
    summary = {**_summary(taus=(0.80, 0.86), ds=(2.1, 2.3)), "paper_test": False,
               "paper_test_differences": differences, "experiment": None,
               "paper_simulation": None, "relative_error": None}
    (run / "summary.json").write_text(json.dumps(summary))
    assert [r["label"] for r in table2_rows(summary)] == ["tcd (this run, mean ± std of 2 samples)"]
    with pytest.warns(FigureWarning, match="fig2.*fig3.*skipped"):
        make_figures(run)
    md = (run / "figures" / "table2.md").read_text()
    assert "0.898" not in md and "0.837" not in md and " %" not in md and "0.830 ± " in md
    assert "rel. error" not in md and "relative error" not in md
    assert ("Not compared with the paper's experiments: this test is not its Leutner test "
            f"({differences[0]}; {differences[1]}).") in md
    assert len((run / "figures" / "table2.csv").read_text().splitlines()) == 2
    # merged with another part of the same study: still not compared
    merged = merge_summaries([(run, summary), (run, {**_summary(taus=(0.9, 1.0), ds=(2.0, 2.1)),
                                                   "samples": [{"seed": 14, "tau_peak_MPa": 0.9,
                                                                "d_peak_mm": 2.0}]})])
    assert merged["paper_test"] is False and merged["relative_error"] is None
    assert merged["paper_test_differences"] == differences
    # parts written before session 49 say nothing: neither does their merge, and the figures
    # judge by the samples' range as for one such run (session 49's review: the merge had said
    # "the paper's test", and a split 0.4 mm study got the experiments' markers)
    old = [{k: v for k, v in x.items() if not k.startswith("paper_test")}
           for x in (summary, _summary())]
    merged = merge_summaries([(run, old[0]), (run, {**old[1], "samples": [
        {"seed": 14, "tau_peak_MPa": 0.9, "d_peak_mm": 2.0}]})])
    assert "paper_test" not in merged and "paper_test_differences" not in merged
    short = figures.SampleCurves("1", run, np.zeros(3), np.array([0.0, 2e-4, 4e-4]), np.ones(3),
                                 np.ones(3), 1e-5, 1.0, 2e-4, 1, {})
    assert figures.is_paper_test(merged, [short]) is False
    assert figures.is_paper_test({**merged, "paper_test": True}, [short]) is True


def test_curves_still_rising_at_their_end_are_named_under_table2_in_fig4_and_in_compare(
        tmp_path, monkeypatch):
    """A sample whose stress still rises at the end of the test has no failure: Table 2 says
    which samples, Fig. 4 marks their last point apart from the peaks, `tcd compare` lists
    them by run."""
    run = tmp_path / "run"
    for seed, (t, d) in {11: (0.80e6, 2.1e-3), 12: (0.90e6, 2.5e-3), 13: (0.83e6, 2.2e-3),
                         14: (0.95e6, 2.485e-3), 15: (0.85e6, 2.46e-3)}.items():
        _write_sample(run, seed, t, d)
    shown = {}

    def keep(fig, path, written):
        if path.name.startswith("fig4"):
            shown["legend"] = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
            shown["markers"] = [line.get_marker() for line in fig.axes[0].get_lines()]
        if path.name == "table2.png":
            shown["table2"] = [t.get_text().replace("\n", " ") for t in fig.texts]
        written.append(path)

    monkeypatch.setattr(figures, "_save", keep)
    with pytest.warns(FigureWarning):
        make_figures(run, tmp_path / "figs", render=False)
    md = (tmp_path / "figs" / "table2.md").read_text()
    # seed 12 rises to the end; seed 14 peaks 0.015 mm before it, within half the 0.05 mm
    # window; seed 15 0.04 mm before it, outside
    assert ("In 2 of the 5 samples (samples 12, 14) the stress still rose at the end of their "
            "curves: each peak lies within half a smoothing window (0.025 mm) of its curve's last "
            "point") in md
    assert md.index("| tcd") < md.index("In 2 of the 5")          # under the table
    assert md.rstrip().splitlines()[-1] in shown["table2"]         # and under the image's
    one = types.SimpleNamespace(seed=7, window=1e-4, peak_at_end=True)
    assert figures.peak_at_end_note([one, types.SimpleNamespace(peak_at_end=False)]) == (
        "In 1 of the 2 samples (sample 7) the stress still rose at the end of its curve: its "
        "peak lies within half a smoothing window (0.05 mm) of the last point, so its τ and d "
        "are that end, not a failure; a longer test would find its peak there or later, as high "
        "or higher.")
    assert "end of a curve still rising\n(no failure by then)" in shown["legend"]
    assert shown["markers"].count(">") == 2 + 1 and shown["markers"].count("o") == 3 + 1
    from tcd import compare
    other = tmp_path / "other"
    _write_sample(other, 11, 0.8e6, 2.1e-3)
    compare.compare_runs([run, other], tmp_path / "cmp", labels=["a", "b"])
    text = (tmp_path / "cmp" / "compare.md").read_text()
    assert ("Curves still rising at their end (the peak within half a smoothing window of the "
            "last point: no failure seen, the peak a lower bound), by run (seeds): a (12, 14).") \
        in text, text


_FULL_DISK = r'''
import io, resource, signal, sys, pathlib
import numpy as np
from tcd import figures
fig = figures._new_figure(7.2, 4.3)
fig.add_subplot().plot(np.random.default_rng(1).normal(size=20000))
buf = io.BytesIO()
fig.savefig(buf, format="pdf")
size = len(buf.getvalue())
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
out = pathlib.Path(sys.argv[1])
for fraction in (0.05, 0.3, 0.6, 0.8, 0.95):
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(fraction * size), resource.RLIM_INFINITY))
    try:
        figures._save(fig, out, [])
        print(fraction, "written")
    except BaseException as exc:
        print(fraction, type(exc).__name__, getattr(exc, "filename", None))
    resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
'''


@pytest.mark.skipif(sys.platform == "win32", reason="file size limits are POSIX")
def test_a_figure_that_the_disk_cannot_hold_fails_as_an_os_error_naming_it(tmp_path):
    """A disk that filled while `tcd figures` or `tcd compare` wrote a PDF ended in a traceback
    (matplotlib's PDF writer failed half way and its clean-up raised zlib.error or
    AttributeError, hiding the OSError; session 72's review on a 150 KB tmpfs). Each figure
    is now drawn in memory and written in one write: a plain OSError naming the figure, and
    nothing left. Here the file size limit cuts the PDF at 5-95 % of its length."""
    import subprocess
    out = tmp_path / "fig.pdf"
    proc = subprocess.run([sys.executable, "-c", _FULL_DISK, str(out)], capture_output=True,
                          text=True, timeout=300, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    lines = proc.stdout.split("\n")[:-1]
    assert proc.returncode == 0 and len(lines) == 5, proc.stdout + proc.stderr
    for line in lines:
        assert line.split(" ", 1)[1] == f"OSError {out}", lines
    assert list(tmp_path.iterdir()) == []
