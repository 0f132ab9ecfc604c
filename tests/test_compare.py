"""`tcd compare`: runs of different scenarios side by side (tcd.compare), on synthetic runs."""
import json
import math

import imageio.v3 as iio
import numpy as np
import pytest

from tcd import compare
from tcd.cli import main
from test_figures import _write_sample

SCENARIO = """\
name = "{name}"
seeds = {seeds}
[bond]
yield_stress_MPa = {yield_}
[[stage]]
kind = "shear"
sample = "{{seed}}.h5"
wall_friction = {friction}
"""


def _run(tmp_path, name, peaks, yield_=1.7, friction=0.3):
    """A finished run directory: one sample per (seed, tau_peak Pa, d_peak m) with a shear
    series, its scenario.toml (the setting varied), and a summary written by this session."""
    run = tmp_path / name
    for seed, tau, d in peaks:
        _write_sample(run, seed, tau, d)
    seeds = [seed for seed, _, _ in peaks]
    (run / "scenario.toml").write_text(SCENARIO.format(name=name, seeds=seeds, yield_=yield_,
                                                       friction=friction))
    (run / "summary.json").write_text(json.dumps({"samples": [
        {"seed": seed, "tau_peak_MPa": tau * 1e-6, "d_peak_mm": d * 1e3} for seed, tau, d in peaks]}))
    return run


def test_compare_tables_each_run_with_the_settings_it_differs_in(tmp_path):
    weak = _run(tmp_path, "weak", [(1, 0.70e6, 2.0e-3), (2, 0.74e6, 2.2e-3)], yield_=1.5)
    strong = _run(tmp_path, "strong", [(1, 0.95e6, 2.4e-3)], yield_=2.0)
    rough = _run(tmp_path, "rough", [(3, 0.90e6, 2.3e-3)], yield_=2.0, friction=0.5)
    out = tmp_path / "cmp"
    written = compare.compare_runs([weak, strong, rough], out, labels=["y1.5", "y2.0", "y2.0 rough"])
    assert sorted(p.name for p in written) == ["compare.csv", "compare.md", "compare.pdf",
                                               "compare.png"]
    md = (out / "compare.md").read_text()
    head = md.splitlines()[2]
    assert "bond.yield_stress_MPa" in head and "stage[1].wall_friction" in head
    assert "seeds" not in head and "name" not in head.replace("run", "")     # not physics
    rows = {line.split(" | ")[0].lstrip("| "): line for line in md.splitlines()[4:7]}
    assert rows["y1.5"].startswith("| y1.5 | 1.5 | 0.3 | 2 | ")
    assert rows["y2.0 rough"].startswith("| y2.0 rough | 2 | 0.5 | 1 | ")
    # the peaks are the series' own (the smoothed curve's), averaged over each run's samples
    table = [line.split(",") for line in (out / "compare.csv").read_text().splitlines()]
    assert table[0][:5] == ["label", "bond.yield_stress_MPa", "stage[1].wall_friction", "n_samples",
                            "tau_peak_MPa"]
    weak_row = dict(zip(table[0], table[1]))
    assert float(weak_row["tau_peak_MPa"]) == pytest.approx(0.72, abs=0.02)
    assert float(weak_row["d_peak_mm"]) == pytest.approx(2.1, abs=0.1)
    assert float(weak_row["tau_peak_std"]) == pytest.approx(0.02, abs=0.01)
    assert dict(zip(table[0], table[2]))["tau_peak_std"] == ""      # one sample: no spread
    assert 0.0 < float(weak_row["bonds_broken_share"]) < 1.0
    image = iio.imread(out / "compare.png")
    assert image.ndim == 3 and image[..., :3].std() > 5


def test_run_numbers_and_mean_curve_of_two_samples(tmp_path):
    from tcd import figures
    run = _run(tmp_path, "r", [(1, 0.8e6, 2.0e-3), (2, 1.0e6, 2.4e-3)])
    _, samples = figures.load_run(run)
    numbers = compare.run_numbers(samples)
    taus = [s.tau_peak * 1e-6 for s in samples]
    assert numbers["n_samples"] == 2
    assert numbers["tau_peak_MPa"] == pytest.approx(np.mean(taus))
    assert numbers["tau_peak_std"] == pytest.approx(np.std(taus))       # population std
    d, tau = compare.mean_curve(samples)
    k = len(d) // 2
    expected = np.mean([np.interp(d[k], s.displacement, s.smoothed) for s in samples])
    assert d[-1] == pytest.approx(2.5e-3) and tau[k] == pytest.approx(expected)


def test_differing_settings_leave_out_a_run_without_scenario():
    a = {"bond": {"yield_stress_MPa": 1.7}, "stage": [{"kind": "shear", "gap_mm": 1.0}]}
    b = {"bond": {"yield_stress_MPa": 1.7}, "stage": [{"kind": "shear", "gap_mm": 0.5}]}
    assert compare.differing_settings([a, b, None]) == ["stage[1].gap_mm"]
    assert compare.differing_settings([a, a]) == []


def test_compare_refuses_what_cannot_be_compared(tmp_path, capsys):
    a = _run(tmp_path, "a", [(1, 0.8e6, 2.0e-3)])
    b = _run(tmp_path / "other", "a", [(1, 0.9e6, 2.1e-3)])
    with pytest.raises(ValueError, match="repeat a name"):
        compare.compare_runs([a, b], tmp_path / "o")
    with pytest.raises(ValueError, match="1 labels for 2 run directories"):
        compare.compare_runs([a, b], tmp_path / "o", labels=["x"])
    assert not (tmp_path / "o").exists()            # nothing written on a refusal
    taken = tmp_path / "taken.png"
    taken.write_bytes(b"an image")
    for command in (["compare", str(a), str(b), "--labels", "x,y"], ["figures", str(a)]):
        assert main(command + ["--out", str(taken)]) == 2
        assert f"--out {taken}: exists and is not a directory" in capsys.readouterr().err
    assert taken.read_bytes() == b"an image"
    assert main(["compare", str(a), "--out", str(tmp_path / "o")]) == 2
    assert "at least two run directories" in capsys.readouterr().err
    assert main(["compare", str(a), str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "no such run directory" in capsys.readouterr().err
    assert main(["compare", str(a), str(b), "--labels", "first,second",
                 "--out", str(tmp_path / "o")]) == 0
    printed = capsys.readouterr().out.split()
    assert str(tmp_path / "o" / "compare.md") in printed
    md = (tmp_path / "o" / "compare.md").read_text()
    assert "| first |" in md and "do not differ" in md and "unfinished" not in md
    (b / "summary.json").unlink()                   # a run still going, or stopped
    assert main(["compare", str(a), str(b), "--labels", "first,second",
                 "--out", str(tmp_path / "o")]) == 0
    assert "No summary.json in second: unfinished" in (tmp_path / "o" / "compare.md").read_text()
    assert math.isfinite(float((tmp_path / "o" / "compare.csv").read_text().splitlines()[1]
                               .split(",")[2]))


def test_long_labels_and_settings_do_not_squeeze_the_plot_away(tmp_path):
    """A label or a differing setting as long as a file path made matplotlib's layout
    collapse the axes (and a `tcd compare` of session 49 take 24 GB): they are shortened and
    wrapped."""
    import warnings
    a = _run(tmp_path, "a", [(1, 0.8e6, 2.0e-3)])
    b = _run(tmp_path, "b", [(1, 0.9e6, 2.1e-3)])
    text = (b / "scenario.toml").read_text()
    (b / "scenario.toml").write_text(text.replace('sample = "{seed}.h5"', 'sample = "'
                                                  + "/very/long/folder" * 12 + '/{seed}.h5"'))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        compare.compare_runs([a, b], tmp_path / "o", labels=["x" * 200, "y"])
    assert "stage[1].sample" in (tmp_path / "o" / "compare.md").read_text()


def _stopped_checkpoint(run, seed, stage, window_mm=0.2, rows=300):
    """A run directory whose sample has no series file, only a checkpoint written in stage
    `stage` of a prepare-then-shear scenario, holding a shear series that rises to 0.8 MPa at
    1.5 mm and falls after (its run went on from another, `branched_from`)."""
    from tcd import io
    d = np.linspace(0.0, 2.0e-3, rows)
    tau = 0.8e6 * np.exp(-((d - 1.5e-3) / 0.8e-3) ** 2)
    text = SCENARIO.format(name="stopped", seeds=[seed], yield_=1.7, friction=0.3)
    text = text.replace("[[stage]]\nkind = \"shear\"",
                        "[[stage]]\nkind = \"prepare\"\n\n[[stage]]\nkind = \"shear\""
                        f"\nsmoothing_window_mm = {window_mm}")
    (run / f"sample_{seed}").mkdir(parents=True)
    (run / "scenario.toml").write_text(text)
    origin = {"run": "/runs/base", "time": 4.59, "displacement_mm": 1.0, "changes": ["x"]}
    io.save_checkpoint(run / f"sample_{seed}" / "checkpoint.h5",
                       {"series/time": d / 1e-3, "series/displacement": d,
                        "series/shear_stress": tau},
                       {"stage": stage, "scenario_text": text,
                        "series_keys": ["time", "displacement", "shear_stress"],
                        "result": {"branched_from": [origin]}})
    return d, tau


def test_compare_draws_a_stopped_shear_as_far_as_its_checkpoint_goes(tmp_path):
    """A shear stopped mid-way has no series file: `tcd compare` reads its series from its
    checkpoint (smoothed over its own stage's window), says it stopped and where it went on
    from; `tcd figures`' reading (a study's Table 2) still leaves it out; a checkpoint of a
    preparation is not a curve."""
    from tcd import figures, io, observables as obs
    done = _run(tmp_path, "done", [(1, 0.85e6, 2.2e-3)])
    stopped = tmp_path / "stopped"
    d, tau = _stopped_checkpoint(stopped, 4, stage=1)
    out = tmp_path / "cmp"
    compare.compare_runs([done, stopped], out, labels=["done", "cut"])
    md = (out / "compare.md").read_text()
    assert ("Shears stopped before the end of their test (no series file: their curves and peaks "
            "so far, from the checkpoint a `--resume` continues from; a higher peak may come "
            "later; a run's means leave them out when it has finished samples), by run: cut "
            "(seed 4 at 2.000 mm).") in md, md
    assert "cut (seed 4) from /runs/base" in md, md
    (row_cut,) = [line for line in md.splitlines() if line.startswith("| cut |")]
    assert " (stopped before the end) | " in row_cut and "(stopped" not in md.split("| cut |")[0]
    peak, at, _ = obs.peak_of(d, tau, 2e-4)
    assert peak == pytest.approx(0.8e6, rel=0.01) and at == pytest.approx(1.5e-3, abs=2e-5)
    row = dict(zip(*[line.split(",") for line in
                     (out / "compare.csv").read_text().splitlines()[::2]]))
    assert float(row["tau_peak_MPa"]) == pytest.approx(peak * 1e-6, rel=1e-5)
    assert float(row["d_peak_mm"]) == pytest.approx(at * 1e3, rel=1e-5)
    (curves,) = figures.load_run(stopped, stopped=True)[1]
    assert curves.stopped and curves.window == pytest.approx(2e-4)
    assert curves.branched_from["run"] == "/runs/base"
    with pytest.raises(ValueError, match="no usable sample"):
        figures.load_run(stopped, [])
    # two stopped shears of one run: listed together under its label
    _stopped_checkpoint(stopped, 5, stage=1, rows=200)
    compare.compare_runs([done, stopped], out, labels=["done", "cut"])
    md = (out / "compare.md").read_text()
    assert "by run: cut (seed 4 at 2.000 mm, seed 5 at 2.000 mm)." in md, md
    # written while the sample was prepared: no shear curve to draw
    prep = tmp_path / "prep"
    _stopped_checkpoint(prep, 5, stage=0)
    with pytest.raises(ValueError, match=r"checkpoint.h5: written in a 'prepare' stage, not a shear"):
        figures.load_stopped_sample("5", prep / "sample_5")
    assert io.checkpoint_arrays(prep / "sample_5" / "checkpoint.h5", ["series/nothing"]) == {}
    # a stage index that is not one (a negative one would read the last stage)
    odd = tmp_path / "odd"
    _stopped_checkpoint(odd, 6, stage=-1)
    with pytest.raises(ValueError, match=r"checkpoint.h5: its stage cannot be read"):
        figures.load_stopped_sample("6", odd / "sample_6")


def test_a_runs_means_leave_out_its_stopped_shears(tmp_path):
    """A run with finished and stopped samples (a study under way): its mean peak, spread and
    mean curve are those of its finished samples (a shear stopped at 2.0 mm with 0.8 MPa
    would pull the mean down); the stopped one is drawn, named, counted apart and not listed
    as a curve still rising; a run of stopped samples only keeps its numbers so far."""
    from tcd import figures
    mixed = tmp_path / "mixed"
    _stopped_checkpoint(mixed, 4, stage=1)
    _write_sample(mixed, 1, 0.95e6, 2.3e-3)
    _write_sample(mixed, 2, 0.85e6, 2.2e-3)
    (mixed / "scenario.toml").write_text(
        (mixed / "scenario.toml").read_text().replace("seeds = [4]", "seeds = [1, 2, 4]"))
    _, samples = figures.load_run(mixed, stopped=True)
    assert sorted((s.seed, s.stopped) for s in samples) == [("1", False), ("2", False), ("4", True)]
    finished = [s for s in samples if not s.stopped]
    numbers = compare.run_numbers(samples)
    assert numbers["n_samples"] == 2 and numbers["n_stopped"] == 1
    assert numbers["tau_peak_MPa"] == pytest.approx(np.mean([s.tau_peak * 1e-6 for s in finished]))
    assert numbers["tau_peak_std"] == pytest.approx(np.std([s.tau_peak * 1e-6 for s in finished]))
    d, _ = compare.mean_curve(samples)
    assert d[-1] == pytest.approx(2.5e-3)           # the stopped one's 2.0 mm does not cut it
    done = _run(tmp_path, "done", [(3, 0.85e6, 2.2e-3)])
    out = tmp_path / "cmp"
    compare.compare_runs([done, mixed], out, labels=["done", "going"])
    md = (out / "compare.md").read_text()
    (row,) = [line for line in md.splitlines() if line.startswith("| going |")]
    assert " | 2 (and 1 stopped, not counted) | " in row and "(stopped before the end)" not in row
    assert f"{numbers['tau_peak_MPa']:.3f} ± {numbers['tau_peak_std']:.3f}" in row
    assert "going (seed 4 at 2.000 mm)" in md and "going (4)" not in md
    csv_rows = [line.split(",") for line in (out / "compare.csv").read_text().splitlines()]
    assert dict(zip(csv_rows[0], csv_rows[2]))["n_stopped"] == "1"
    # only stopped samples: their numbers so far, marked as such
    only = compare.run_numbers([s for s in samples if s.stopped])
    assert only["n_samples"] == 1 and only["n_stopped"] == 0
    assert only["tau_peak_MPa"] == pytest.approx(0.8, rel=0.01)


def test_compare_seeds_takes_the_same_samples_of_each_run(tmp_path, capsys):
    """`--seeds`: only those samples of each run (a study at two settings, compared on the
    samples both have); a run without any of them is refused, naming what it has."""
    from tcd import figures
    five = _run(tmp_path, "five", [(s, (0.80 + 0.02 * s) * 1e6, 2.2e-3) for s in range(1, 6)])
    three = _run(tmp_path, "three", [(s, (0.85 + 0.02 * s) * 1e6, 2.3e-3) for s in (2, 3, 4)],
                 yield_=1.6)
    out = tmp_path / "cmp"
    assert main(["compare", str(five), str(three), "--seeds", "2,4", "--out", str(out)]) == 0
    md = (out / "compare.md").read_text()
    rows = {line.split(" | ")[0].lstrip("| "): line.split(" | ") for line in md.splitlines()
            if line.startswith("| five |") or line.startswith("| three |")}
    assert rows["five"][2] == "2" and rows["three"][2] == "2"      # after the yield column
    _, every = figures.load_run(five)
    taken = [s.tau_peak * 1e-6 for s in every if s.seed in ("2", "4")]
    assert rows["five"][3] == f"{np.mean(taken):.3f} ± {np.std(taken):.3f}"
    assert "Only the samples of seeds 2, 4 (`--seeds`), by run: five (2, 4); three (2, 4)." in md
    # a seed given twice is one seed ("seeds 2, 2, 4" before session 72)
    assert main(["compare", str(five), str(three), "--seeds", "2,2,4", "--out",
                 str(tmp_path / "twice")]) == 0
    assert ((tmp_path / "twice" / "compare.md").read_text().split("|")[-1]
            == md.split("|")[-1].replace(str(out), str(tmp_path / "twice")))
    # none of the seeds in a run: refused, nothing written
    assert main(["compare", str(five), str(three), "--seeds", "5", "--out",
                 str(tmp_path / "none")]) == 2
    assert "three: none of the seeds 5 (its samples: 2, 3, 4)" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()
    assert main(["compare", str(five), str(three), "--seeds", "x", "--out", str(out)]) == 2
    assert "expected comma-separated integer seeds" in capsys.readouterr().err


def test_compare_says_whether_the_runs_sheared_the_same_sample_files(tmp_path):
    """By the SHA-256 each run's summary recorded of the files it sheared (`inputs`): the
    same files seed by seed whatever the paths' spelling, or different ones under one path
    (a sample made again); nothing said when fewer than two runs recorded them."""
    def recorded(run, digests):
        summary = json.loads((run / "summary.json").read_text())
        for smp in summary["samples"]:
            smp["inputs"] = {"0:shear": {"path": f"/x/{smp['seed']}.h5", "bytes": 1,
                                         "sha256": digests[smp["seed"]]}}
        (run / "summary.json").write_text(json.dumps(summary))

    a = _run(tmp_path, "a", [(1, 0.80e6, 2.1e-3), (2, 0.82e6, 2.2e-3)])
    b = _run(tmp_path, "b", [(1, 0.85e6, 2.2e-3), (2, 0.86e6, 2.3e-3)], yield_=1.8)
    out = tmp_path / "cmp"
    compare.compare_runs([a, b], out)
    assert "Sample files sheared" not in (out / "compare.md").read_text()   # none recorded
    recorded(a, {1: "f1", 2: "f2"})
    compare.compare_runs([a, b], out)
    assert "Sample files sheared" not in (out / "compare.md").read_text()   # one run only
    recorded(b, {1: "f1", 2: "g2"})
    compare.compare_runs([a, b], out)
    md = (out / "compare.md").read_text()
    assert ("Sample files sheared, by the SHA-256 each run recorded (a, b): the same files for "
            "seeds 1 (0:shear); **different files** for seeds 2 (0:shear).") in md, md
    compare.compare_runs([a, b], out, seeds=[1])                # only the samples compared
    assert "the same files for seeds 1 (0:shear)." in (out / "compare.md").read_text()


def test_two_spellings_of_one_sample_file_are_one_setting(tmp_path):
    """A run whose run.json names its scenario file (since session 58) has its relative sample
    path read from that file's folder, as the run read it: a run of `../samples/{seed}.h5`
    from `study/s.toml` and one of `/abs/.../samples/{seed}.h5` do not differ in the sample,
    and `tcd figures` takes them as parts of one study."""
    from tcd import figures
    rel = _run(tmp_path, "rel", [(1, 0.85e6, 2.2e-3)])
    absolute = _run(tmp_path, "abs", [(2, 0.86e6, 2.3e-3)])
    for run, sample in ((rel, "../samples/{seed}.h5"),
                        (absolute, str(tmp_path / "samples" / "{seed}.h5"))):
        text = (run / "scenario.toml").read_text().replace('"{seed}.h5"', f'"{sample}"')
        (run / "scenario.toml").write_text(text)
    both = (rel, absolute)
    assert compare.differing_settings(figures.scenarios_of(both)) == [
        "stage[1].sample"]                  # no record of where the scenario file was
    (rel / "run.json").write_text(json.dumps({"scenario_file": str(tmp_path / "study" / "s.toml")}))
    assert compare.differing_settings(figures.scenarios_of(both)) == [
        "stage[1].sample"]                  # one run's folder alone: each as written
    (absolute / "run.json").write_text(json.dumps({"scenario_file": "/elsewhere/t.toml"}))
    assert compare.differing_settings(figures.scenarios_of(both)) == []
    figures.check_one_study(list(both))     # parts of one study: no error
    compare.compare_runs(list(both), tmp_path / "cmp")
    assert "| stage[1].sample |" not in (tmp_path / "cmp" / "compare.md").read_text()
    (rel / "run.json").write_text(json.dumps({"scenario_file": str(tmp_path / "x" / "y" / "s.toml")}))
    assert compare.differing_settings(figures.scenarios_of(both)) == [
        "stage[1].sample"]                  # another file: a setting that differs
    with pytest.raises(ValueError, match="ran another scenario"):
        figures.check_one_study(list(both))
    # an older part (no record) and a newer one of one study, the same relative path as
    # written: still one study, as before the record
    (absolute / "scenario.toml").write_text((rel / "scenario.toml").read_text())
    (absolute / "run.json").write_text("{}")
    figures.check_one_study(list(both))


def test_target_peak_finds_the_setting_that_gives_a_peak(tmp_path, capsys):
    """`--target-peak`: the value of the one numeric setting the runs differ in at which the
    mean peak would be the target, interpolated between the two runs that bracket it (their
    peaks as compare.csv gives them), or extrapolated on the least-squares line, said so."""
    runs = [_run(tmp_path, f"y{y}", [(1, (tau - 0.01) * 1e6, 2.0e-3), (2, (tau + 0.01) * 1e6, 2.2e-3)],
                 yield_=y) for y, tau in ((1.5, 0.80), (1.8, 0.95), (1.6, 0.86))]
    out = tmp_path / "cmp"
    assert main(["compare", *map(str, runs), "--target-peak", "0.9", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    table = [line.split(",") for line in (out / "compare.csv").read_text().splitlines()]
    rows = {row[0]: dict(zip(table[0], row)) for row in table[1:]}
    (x0, y0, d0), (x1, y1, d1) = [(float(rows[k]["bond.yield_stress_MPa"]),
                                   float(rows[k]["tau_peak_MPa"]), float(rows[k]["d_peak_mm"]))
                                  for k in ("y1.6", "y1.8")]
    assert y0 < 0.9 < y1
    expected = x0 + (0.9 - y0) / (y1 - y0) * (x1 - x0)
    assert "bond.yield_stress_MPa at which the mean peak would be 0.9 MPa" in printed
    assert f"{expected:.4g} (the peak at {d0 + (0.9 - y0) / (y1 - y0) * (d1 - d0):.3g} mm)" in printed
    assert "**" not in printed and f"**{expected:.4g}**" in (out / "compare.md").read_text()
    assert "Caveats" not in printed                 # same seeds, finished, nothing else differs
    from tcd import figures
    loaded = []
    for r in runs:
        _, samples = figures.load_run(r)
        loaded.append({"label": r.name, "samples": samples, **compare.run_numbers(samples),
                       "scenario": figures.scenarios_of([r])[0]})
    fit = compare.calibrate(loaded, ["bond.yield_stress_MPa"], 0.9)
    assert fit["values"] == [pytest.approx(expected)] and not fit["extrapolated"]
    slope = np.polyfit([1.5, 1.8, 1.6], [r["tau_peak_MPa"] for r in loaded], 1)[0]
    assert fit["slope"] == pytest.approx(slope) and 0.4 < slope < 0.6
    # beyond the runs' peaks: the least-squares line, called an extrapolation
    high = compare.calibrate(loaded, ["bond.yield_stress_MPa"], 1.2)
    assert high["extrapolated"] and high["values"][0] > 1.8 and "an extrapolation" in high["text"]
    # peaks that rise and fall with the setting: every crossing
    loaded[1]["tau_peak_MPa"] = 0.70                # 1.8 now below the target again
    both = compare.calibrate(loaded, ["bond.yield_stress_MPa"], 0.85)
    assert len(both["values"]) == 2 and both["values"][0] < 1.6 < both["values"][1] < 1.8


def test_target_peak_refuses_what_it_cannot_fit(tmp_path, capsys):
    a = _run(tmp_path, "a", [(1, 0.8e6, 2.0e-3)], yield_=1.5, friction=0.3)
    b = _run(tmp_path, "b", [(1, 0.9e6, 2.1e-3), (2, 0.9e6, 2.1e-3)], yield_=1.7, friction=0.5)
    same = _run(tmp_path, "same", [(1, 0.9e6, 2.1e-3)], yield_=1.5, friction=0.3)
    out = tmp_path / "o"
    for command, message in (
            ([a, b, "--target-peak", "0.85"], "differ in 2 numeric settings "
             "(bond.yield_stress_MPa, stage[1].wall_friction): name the one to fit with --fit-setting"),
            ([a, same, "--target-peak", "0.85"], "differ in no numeric setting"),
            ([a, b, "--target-peak", "0.85", "--fit-setting", "bond.gap_mm"],
             "--fit-setting bond.gap_mm: the runs do not differ in it"),
            ([a, b, "--fit-setting", "bond.yield_stress_MPa"], "give --target-peak MPa too"),
            ([a, b, "--target-peak", "-1", "--fit-setting", "bond.yield_stress_MPa"],
             "expected a positive stress")):
        assert main(["compare", *map(str, command), "--out", str(out)]) == 2
        assert message in capsys.readouterr().err
        assert not out.exists()                     # nothing written on a refusal
    assert main(["compare", str(a), str(b), "--target-peak", "0.85", "--fit-setting",
                 "bond.yield_stress_MPa", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "**" not in printed and "1.6 (the peak at" in printed
    assert ("Caveats: the runs' means are over different samples (`--seeds` takes the same ones); "
            "the runs also differ in stage[1].wall_friction, which the fit ignores.") in printed


def test_a_run_without_its_scenario_file_is_read_from_its_samples_or_named(tmp_path, capsys):
    """A run whose scenario.toml was missing or unreadable was left out of the settings, and
    compare.md said "The runs' scenarios do not differ", --target-peak that they differed in no
    setting (session 72's review). Now its samples' recorded scenario stands in for it, and
    where none is left the run is named: a warning, a line in compare.md, a refused fit."""
    from tcd import io
    a = _run(tmp_path, "a", [(1, 0.8e6, 2.0e-3)], friction=0.3)
    b = _run(tmp_path, "b", [(1, 0.9e6, 2.1e-3)], friction=0.5)
    text = (b / "scenario.toml").read_text()
    (b / "scenario.toml").unlink()
    io.append_frame(b / "sample_1" / "states.h5", {
        "particles/x": np.zeros((1, 3)), "particles/radius": np.full(1, 1e-3)},
        time=0.0, step=0, stage="shear", scenario_text=text)
    out = tmp_path / "o"
    assert main(["compare", str(a), str(b), "--out", str(out)]) == 0
    md = (out / "compare.md").read_text()
    assert "stage[1].wall_friction" in md and "do not differ" not in md
    (b / "sample_1" / "states.h5").unlink()
    (b / "scenario.toml").write_text("not = [toml")
    capsys.readouterr()
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "p")]) == 0
    err = capsys.readouterr().err
    assert f"{b / 'scenario.toml'} missing or unreadable" in err, err
    md = (tmp_path / "p" / "compare.md").read_text()
    assert "The scenario of b is not known" in md and "do not differ" not in md
    assert main(["compare", str(a), str(b), "--target-peak", "0.85", "--out",
                 str(tmp_path / "q")]) == 2
    assert "the scenario of b (" in capsys.readouterr().err
    assert not (tmp_path / "q").exists()
