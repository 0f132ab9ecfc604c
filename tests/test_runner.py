"""End to end through `tcd run`: outputs, resume after a kill, crash-safe files (issue 4)."""
import contextlib
import csv
import json
import math
import os
import pathlib
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from conftest import default_stop_signals, run_tcd
from tcd import backend, io
from tcd import observables as obs

ROOT = pathlib.Path(__file__).resolve().parents[1]

MICRO = """
name = "micro"
seeds = [3]
[solver]
time_step = 5e-4
max_sweeps = 500
[output]
snapshot_every = 0.05
checkpoint_every_s = 0.5
[[stage]]
kind = "prepare"
cylinder_diameter_mm = 24.0
layer_height_mm = 4.0
particles_per_layer = 40
size_scale = 0.3
courses = ["binder", "surface"]
column_height_mm = 100.0
lattice_jitter_mm = 0.05
settle_speed = 0.02
max_settle_time = 0.3
vibration_amplitude_mm = 0.5
vibration_duration = 0.05
sample_height_mm = 8.0
max_hold_time = 0.1
[[stage]]
kind = "shear"
displacement_mm = 0.2
velocity_mm_per_min = 600.0
ring_height_mm = 4.0
gap_mm = 0.3
smoothing_window_mm = 0.02
"""


def load_here(path):
    """The scenario at `path` on the session's backend (as run_tcd)."""
    from tcd.config import load_scenario
    return load_scenario(str(path)).with_overrides(arch=backend.arch(),
                                                    precision=backend.precision())


@pytest.fixture(scope="module")
def micro_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("micro")
    scenario = d / "micro.toml"
    scenario.write_text(MICRO)
    out = d / "out"
    assert run_tcd(["run", str(scenario), "--out", str(out)]) == 0
    return scenario, out


def test_tiny_scenario_runs_end_to_end_through_tcd_run(tmp_path):
    out = tmp_path / "tiny"
    assert run_tcd(["run", str(ROOT / "scenarios" / "tiny.toml"), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    s = summary["samples"][0]
    assert s["particles"] == 180
    assert s["bonds_total"] > 100
    assert np.isfinite(s["tau_peak_MPa"]) and s["tau_peak_MPa"] > 0
    # not the paper's test: not compared with its experiments, and the summary says why
    shear = s["stages"]["1:shear"]
    assert shear["mould_diameter_mm"] == pytest.approx(30.0)
    assert summary["paper_test"] is False
    assert summary["experiment"] is summary["relative_error"] is summary["paper_simulation"] is None
    assert [x.split(" (")[0] for x in summary["paper_test_differences"]] == [
        "a shear at 600 mm/min", "a shear to 0.4 mm",
        "a mould of 30 mm", f"a sample height of {shear['sample_height_mm']:.4g} mm"]
    sample = out / "sample_1"
    stages = [io.read_frame(sample / "states.h5", k)["stage"] for k in range(io.frame_count(sample / "states.h5"))]
    assert "prepare" in stages and "shear" in stages
    series = io.read_series(sample / "shear_series.h5")
    assert len(series["shear_stress"]) == len(series["displacement"]) > 10
    assert (sample / "shear_series.csv").read_text().splitlines()[0].startswith("time [s]")
    assert "frames" in io.info(sample / "states.h5")
    # what a reader needs to make sense of the files (session 50's output audit): the series'
    # codes and units, every array of the prepared sample with its units, and no made-up
    # breakage point for a bond that never broke
    import h5py
    with h5py.File(sample / "prepare_series.h5") as f:
        assert f.attrs["phase_names"] == "0 pour, 1 vibrate, 2 hold, 3 confine"
        assert set(np.unique(f["phase"][()])) == {0, 1, 2, 3}
    with h5py.File(sample / "shear_series.h5") as f:
        assert f.attrs["tau_peak"] == pytest.approx(s["tau_peak_MPa"] * 1e6)
        assert [f.attrs[k + "_units"] for k in ("tau_peak", "d_peak", "smoothing_window")] == [
            "Pa", "m", "m"]
    for name in ("prepared.h5", "checkpoint.h5"):
        with h5py.File(sample / name) as f:
            units = {}
            f["arrays"].visititems(lambda key, ds: units.setdefault(key, ds.attrs.get("units"))
                                   if isinstance(ds, h5py.Dataset) else None)
        assert units and units == {k: io.STATE_UNITS[k] for k in units}, name
    last = io.read_frame(sample / "states.h5", -1)
    intact = last["bonds/state"] == io.BOND_INTACT
    assert intact.any() and (~intact).any()
    assert np.all(np.isnan(last["bonds/broken_position"][intact]))
    assert np.all(np.isfinite(last["bonds/broken_position"][~intact]))
    # refuses to overwrite a finished run without --resume
    assert run_tcd(["run", str(ROOT / "scenarios" / "tiny.toml"), "--out", str(out)]) == 2


def test_shear_series_is_the_ring_force_over_the_sample_section(micro_run):
    """The Leutner shear's measure (PHYSICS.md section 8): tau = F_x / (pi R^2), R the mould's
    inner radius (12 mm here), F_x the force the grains exert against the moving upper ring's
    motion; the displacement is the ring's imposed travel, 600 mm/min from the start of the
    shear to 0.2 mm (a diameter for the radius would be a factor 4, the lower ring's force the
    opposite sign)."""
    _, out = micro_run
    s = io.read_series(out / "sample_3" / "shear_series.h5")
    force, stress = np.asarray(s["shear_force"]), np.asarray(s["shear_stress"])
    np.testing.assert_allclose(stress, force / (math.pi * 0.012**2), rtol=1e-12)
    t, d = np.asarray(s["time"]), np.asarray(s["displacement"])
    np.testing.assert_allclose(np.diff(d) / np.diff(t), 0.6 / 60.0, rtol=1e-9)
    assert d[-1] == pytest.approx(0.2e-3, rel=1e-6) and d[0] < 0.01e-3
    half = len(force) // 2
    assert np.mean(force[half:]) > 0          # the grains hold the ring back


def test_courses_as_built_are_their_tops_when_their_hold_ended(micro_run):
    """Each course's height as built is read when its own hold ends: its grains' top (never
    above the plate that holds them), from the top the course below had at its own end."""
    _, out = micro_run
    sample = json.loads((out / "sample_3" / "summary.json").read_text())
    holds = [rec for rec in sample["phases"] if rec["phase"] == "hold"]
    assert [rec["layer"] for rec in holds] == [0, 1]
    arrays, _ = io.load_checkpoint(out / "sample_3" / "prepared.h5")
    slack = 1e3 * 0.01 * 2 * arrays["particles/radius"].min()
    for rec in holds:
        assert 0.0 < rec["course_top_mm"] <= rec["plate_mm"] + slack
    built = sample["stages"]["0:prepare"]["course_heights_as_built_mm"]
    assert built[0] == pytest.approx(holds[0]["course_top_mm"], rel=1e-12)
    assert built[1] == pytest.approx(holds[1]["course_top_mm"] - holds[0]["course_top_mm"], rel=1e-12)
    # read by the highest grain (where a plate lowered onto the course rests): at or above
    # the 99th percentile, never through the plate
    for rec in holds:
        assert rec["course_top_mm"] <= rec["course_highest_top_mm"] <= rec["plate_mm"] + slack
    top = sample["stages"]["0:prepare"]["course_heights_as_built_by_highest_grain_mm"]
    assert top[0] == pytest.approx(holds[0]["course_highest_top_mm"], rel=1e-12)
    assert top[1] == pytest.approx(holds[1]["course_highest_top_mm"] - holds[0]["course_highest_top_mm"],
                                   rel=1e-12)


def test_prepared_file_keeps_its_courses_as_built(micro_run, benchmark_script, capsys):
    """prepared.h5 carries the preparation's phase records: benchmarks/sample_table.py, which
    reads only the file, reports the same courses as built as the run's summary."""
    scenario, out = micro_run
    table = benchmark_script("sample_table")
    numbers = table.sample_numbers(load_here(scenario), out / "sample_3" / "prepared.h5")
    sample = json.loads((out / "sample_3" / "summary.json").read_text())
    built = sample["stages"]["0:prepare"]["course_heights_as_built_mm"]
    assert numbers["course_heights_as_built_mm"] == pytest.approx(built, rel=1e-12)
    assert table.main([str(scenario), str(out / "sample_3" / "prepared.h5"),
                       "--precision", backend.precision()]) == 0
    row = capsys.readouterr().out.splitlines()[2]
    prep = sample["stages"]["0:prepare"]
    top, end = prep["course_heights_as_built_by_highest_grain_mm"], prep["course_heights_by_highest_grain_mm"]
    assert row.endswith(f"| {built[0]:.1f} / {built[1]:.1f} | {top[0]:.1f} / {top[1]:.1f} | "
                        f"{end[0]:.1f} / {end[1]:.1f} | "
                        f"{prep['highest_grain_top_mm']:.1f}, "
                        f"{prep['top_plate_gap_mm']:.1f} | {prep['packing_fraction_below_highest_grain']:.3f} |")


def test_courses_as_built_from_phase_records():
    from tcd.protocols import Prepare
    recs = [{"phase": "pour", "layer": 0}, {"phase": "hold", "layer": 0, "course_top_mm": 59.0},
            {"phase": "hold", "layer": 1, "course_top_mm": 119.5}, {"phase": "confine", "layer": 1}]
    assert Prepare.as_built(recs, 2) == pytest.approx([59.0, 60.5])
    # a run resumed from a checkpoint written before the record existed: nothing made up
    assert Prepare.as_built(recs[2:], 2) == [None, None]
    assert Prepare.as_built(recs[:2], 2) == [59.0, None]
    recs[1]["course_highest_top_mm"], recs[2]["course_highest_top_mm"] = 59.6, 119.2
    assert Prepare.as_built(recs, 2, "course_highest_top_mm") == pytest.approx([59.6, 59.6])
    assert Prepare.as_built(recs, 2) == pytest.approx([59.0, 60.5])


def test_same_scenario_same_numbers_with_parallel_samples(micro_run, tmp_path):
    """Seed 3 again, this time next to seed 4 in two worker processes (--jobs 2): seed 3's
    numbers are bit-identical to the single-process run."""
    scenario, out = micro_run
    two = tmp_path / "two.toml"
    two.write_text(MICRO.replace("seeds = [3]", "seeds = [3, 4]"))
    again = tmp_path / "again"
    assert run_tcd(["run", str(two), "--out", str(again), "--jobs", "2"]) == 0
    a, _ = io.load_checkpoint(out / "sample_3" / "checkpoint.h5")
    b, _ = io.load_checkpoint(again / "sample_3" / "checkpoint.h5")
    for key in ("particles/x", "particles/v", "bonds/state", "bonds/impulse"):
        assert np.array_equal(a[key], b[key]), key
    summary = json.loads((again / "summary.json").read_text())
    assert [s["seed"] for s in summary["samples"]] == [3, 4] and summary["jobs"] == 2
    assert summary["samples"][1]["particles"] > 0 and (again / "sample_4" / "prepared.h5").exists()


def test_killed_run_resumes_to_the_same_final_state(micro_run, tmp_path):
    from tcd import runner
    scenario, out = micro_run
    killed = tmp_path / "killed"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "tcd.cli", "run", str(scenario), "--out", str(killed),
           "--arch", backend.arch(), "--precision", backend.precision()]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ck = killed / "sample_3" / "checkpoint.h5"
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if ck.exists():
            _, meta = io.load_checkpoint(ck)
            if meta["stage"] == 0 and meta["phase_index"] >= 1:
                break
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (killed / "summary.json").exists()
    # what was written before the kill is readable
    assert io.frame_count(killed / "sample_3" / "states.h5") >= 1
    # `tcd info RUN_DIR` says where the sample stopped, from its checkpoint
    _, meta = io.load_checkpoint(ck)
    info = runner.run_info(killed)
    where = (f"phase {meta['phase_index'] + 1} ({meta['phase']['name']!r} of layer "
             f"{meta['phase']['info']['layer'] + 1}) at step {meta['step_in_phase']} of "
             f"{'at most ' if meta['phase']['settle'] else ''}{meta['phase']['steps']}, "
             if meta["phase"] else f"before its phase {meta['phase_index'] + 1}, ")
    assert f"sample_3: stopped in stage 1 of 2 (prepare), {where}" in info, info
    assert f"t = {meta['time']:.4f} s; checkpoint checkpoint.h5 written 20" in info, info
    assert "run summary: not written yet" in info and "--resume" in info, info
    assert "running now" not in info, info
    assert run_tcd(["run", str(scenario), "--out", str(killed), "--resume"]) == 0
    a, _ = io.load_checkpoint(out / "sample_3" / "checkpoint.h5")
    b, _ = io.load_checkpoint(killed / "sample_3" / "checkpoint.h5")
    for key in a:
        assert np.array_equal(a[key], b[key], equal_nan=a[key].dtype.kind == "f"), key
    sa = json.loads((out / "summary.json").read_text())["samples"][0]
    sb = json.loads((killed / "summary.json").read_text())["samples"][0]
    assert sa["tau_peak_MPa"] == sb["tau_peak_MPa"] and sa["d_peak_mm"] == sb["d_peak_mm"]
    # each invocation's loop mode (with fast math on the last bits follow it): the same, twice
    assert sa["cpu_loops"] == [backend.loop_mode()]
    assert sb["cpu_loops"] == [backend.loop_mode()] * 2


def test_tcd_info_of_a_run_directory_tells_each_samples_state(micro_run, tmp_path, capsys):
    """`tcd info RUN_DIR`: a finished sample's numbers (those of its summary), a seed not
    started, a process writing into the run now; a directory that is not a run is refused."""
    from tcd import runner
    scenario, out = micro_run
    from tcd import cli
    assert cli.main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "sample_3" / "summary.json").read_text())
    assert text.startswith(f"{out}: tcd run of scenario 'micro' ({out / 'scenario.toml'}): "
                           "stages prepare, shear; seeds 3\n"), text
    assert f"backend: {backend.arch()} {backend.precision()}, tcd " in text, text
    # whether the curve still rose at its end, from the series itself
    series = io.read_series(out / "sample_3" / "shear_series.h5")
    window = res["stages"]["1:shear"]["smoothing_window_mm"]
    assert res["peak_at_end"] is bool(1e3 * series["displacement"].max() - res["d_peak_mm"]
                                      < 0.5 * window)
    rising = " (the end of the test: still rising, no failure)" if res["peak_at_end"] else ""
    assert (f"sample_3: done: {res['particles']} grains, peak {res['tau_peak_MPa']:.4g} MPa at "
            f"{res['d_peak_mm']:.3g} mm{rising}, {res['bonds_broken']} of {res['bonds_total']} bonds "
            f"broken, packing fraction {res['packing_fraction']:.3f}, "
            f"{sum(res['wall_time_s'].values()):.0f} s of wall time\n") in text, text
    assert f"run summary: {out / 'summary.json'}" in text
    # a sample whose stress still rose at the end of the test is told apart from a failure
    ended = tmp_path / "ended.json"
    ended.write_text(json.dumps({**res, "peak_at_end": True}))
    assert (f"peak {res['tau_peak_MPa']:.4g} MPa at {res['d_peak_mm']:.3g} mm (the end of the "
            "test: still rising, no failure), ") in runner._done_line(ended)
    import shutil
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "summary.json").unlink()
    (copy / "scenario.toml").write_text(
        (copy / "scenario.toml").read_text().replace("seeds = [3]", "seeds = [3, 7]"))
    with runner.run_lock(copy):
        text = runner.run_info(copy)
    assert "sample_7: not started" in text, text
    assert f"running now: a tcd process writes into it (pid {os.getpid()} on " in text, text
    assert "run summary: not written yet\n" not in text and text.endswith("not written yet"), text
    assert "running now" not in runner.run_info(copy)
    assert cli.main(["info", str(tmp_path)]) == 2
    assert "not a tcd run directory (it has no scenario.toml" in capsys.readouterr().err


def test_a_study_split_with_seeds_into_one_folder_sums_up_every_finished_sample(micro_run,
                                                                                  tmp_path):
    """`--seeds 3`, then `--seeds 4 --resume` into the same --out: the run's summary.json held
    seed 4 alone, its statistics over one sample (the determinism audit of session 48)."""
    import shutil
    scenario, out = micro_run
    split = tmp_path / "split"
    shutil.copytree(out, split)
    # seed 4 finished by an earlier invocation (its files: seed 3's, renamed)
    shutil.copytree(split / "sample_3", split / "sample_4")
    res4 = json.loads((split / "sample_4" / "summary.json").read_text())
    res4.update(seed=4, tau_peak_MPa=2 * res4["tau_peak_MPa"])
    (split / "sample_4" / "summary.json").write_text(json.dumps(res4))
    both = tmp_path / "both.toml"
    both.write_text(scenario.read_text().replace("seeds = [3]", "seeds = [3, 4]"))
    assert run_tcd(["run", str(both), "--out", str(split), "--seeds", "3", "--resume"]) == 0
    summary = json.loads((split / "summary.json").read_text())
    assert [smp["seed"] for smp in summary["samples"]] == [3, 4]
    tau3 = summary["samples"][0]["tau_peak_MPa"]
    assert summary["mean"]["tau_peak_MPa"] == pytest.approx(1.5 * tau3)
    assert summary["std"]["tau_peak_MPa"] == pytest.approx(0.5 * tau3)


def test_each_stage_reports_its_steps_at_the_sweep_cap(micro_run):
    """A stage's summary counts the steps that stopped at max_sweeps and its largest residual
    (the user audit of session 48: a third of a preparation's steps at the cap, unsaid)."""
    _, out = micro_run
    res = json.loads((out / "sample_3" / "summary.json").read_text())
    for key, kind in (("0:prepare", "prepare"), ("1:shear", "shear")):
        series = io.read_series(out / "sample_3" / f"{kind}_series.h5")
        numbers = res["stages"][key]
        sweeps = np.asarray(series["sweeps"])
        assert numbers["recorded_steps"] == len(sweeps) == numbers["steps"]
        assert numbers["steps_at_sweep_cap"] == int(np.count_nonzero(sweeps >= 500))
        assert numbers["largest_residual"] == float(np.max(series["residual"]))
    assert res["stages"]["0:prepare"]["steps_at_sweep_cap"] > 0     # the micro run's jammed bed


def test_resume_without_checkpoint_is_refused(tmp_path):
    scenario = tmp_path / "micro.toml"
    scenario.write_text(MICRO)
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "nothing"), "--resume"]) == 2


def test_resume_restores_the_wall_forces_a_servo_plate_reads(tmp_path):
    """The preparation's servo plate reads the force of the last step before it moves, so a
    resumed run must start with the wall forces the checkpoint holds (a kill during a hold
    phase once gave a different sample)."""
    from tcd import config, runner
    from tcd.simulation import Simulation
    from tcd.walls import plane
    scn = config.parse_scenario(MICRO)
    r = 0.002
    x = np.array([[0.0, 0.0, r], [0.0, 0.0, 3 * r], [0.0, 0.0, 5 * r]])
    walls = [plane((0, 0, 0), (0, 0, 1), name="floor"),
             plane((0, 0, 6 * r), (0, 0, -1), name="top", motion="constant", velocity=(0, 0, -1e-3))]
    a = Simulation([r] * 3, x, walls=walls, settings=scn.solver.to_settings(), density=scn.material.density,
                   friction=scn.material.friction,
                   domain=((-0.01, -0.01, -0.01), (0.01, 0.01, 0.03)))
    a.step(20)
    assert a.wall_force(0)[2] < 0 and a.wall_force(1)[2] > 0     # both plates carry the column
    path = tmp_path / "checkpoint.h5"
    io.save_checkpoint(path, a.state_dict(), {"walls": [w.to_dict() for w in a.walls], "time": a.time,
                                              "step": a.step_index, "domain": [list(a.domain[0]), list(a.domain[1])]})
    b = runner.restore_simulation(scn, *io.load_checkpoint(path))
    for k in range(2):
        assert np.array_equal(a.wall_force(k), b.wall_force(k)), k
    a.step(5)
    b.step(5)
    assert np.array_equal(a.positions(), b.positions())


def test_shear_from_the_saved_sample_equals_the_study_in_one_run(micro_run, tmp_path):
    """A study in two parts (prepare, then shear from the saved `prepared.h5` with `sample =`),
    as scenarios/leutner_prepare.toml + leutner_shear.toml split scenarios/leutner.toml, gives
    the same shear as preparing and shearing in one run."""
    scenario, out = micro_run
    prepared = out / "sample_3" / "prepared.h5"
    head = MICRO[:MICRO.index('[[stage]]\nkind = "prepare"')]
    shear = MICRO[MICRO.index('[[stage]]\nkind = "shear"'):]
    text = head + shear.replace('kind = "shear"', f'kind = "shear"\nsample = "{prepared.as_posix()}"', 1)
    part = tmp_path / "shear_only.toml"
    part.write_text(text)
    assert run_tcd(["run", str(part), "--out", str(tmp_path / "two")]) == 0
    one = io.read_series(out / "sample_3" / "shear_series.h5")
    two = io.read_series(tmp_path / "two" / "sample_3" / "shear_series.h5")
    assert len(one["shear_stress"]) == len(two["shear_stress"]) > 10
    for key in ("displacement", "shear_stress", "bonds_intact", "bonds_broken_shear"):
        assert np.array_equal(one[key], two[key]), key
    a = json.loads((out / "sample_3" / "summary.json").read_text())
    b = json.loads((tmp_path / "two" / "sample_3" / "summary.json").read_text())
    assert a["bonds_total"] == b["bonds_total"] > 0
    assert a["tau_peak_MPa"] == b["tau_peak_MPa"]
    # the shear from a file records which file it read, and what was in it
    record = b["inputs"]["0:shear"]
    assert record == io.file_record(prepared) and record["path"] == str(prepared.resolve())
    assert len(record["sha256"]) == 64 and record["bytes"] == prepared.stat().st_size
    assert "inputs" not in a                  # prepared in the same run: no input file


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_ctrl_c_checkpoints_at_the_step_it_stopped_and_resumes_to_the_same_end(micro_run, tmp_path,
                                                                                monkeypatch, signum):
    """Ctrl-C (SIGINT), SIGTERM (`kill`, a batch scheduler ending a job) or SIGHUP (the
    terminal closed; it used to end the run at once: session 70's probe) takes effect at
    the end of the step: a checkpoint of that step is written (here no periodic one would have
    been), the run raises KeyboardInterrupt, and --resume ends with the same numbers as the
    uninterrupted run."""
    from tcd import config, runner
    from tcd.simulation import Simulation
    scenario, out = micro_run
    text = MICRO.replace("checkpoint_every_s = 0.5", "checkpoint_every_s = 1e6")
    scn = config.parse_scenario(text, "<micro>")
    real_step = Simulation.step
    calls = {"n": 0}

    def step_then_ctrl_c(self, count=1):
        calls["n"] += 1
        if calls["n"] == 37:
            os.kill(os.getpid(), signum)             # arrives inside the loop, between steps
        return real_step(self, count)
    monkeypatch.setattr(Simulation, "step", step_then_ctrl_c)
    # the defaults, as in a terminal: Python's own SIGINT handler (a background shell, as CI
    # may be, ignores SIGINT), SIGTERM's default action (to end the process)
    default = signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL
    outer = signal.signal(signum, default)
    try:
        with pytest.raises(KeyboardInterrupt):
            runner.run_sample(scn, 3, tmp_path / "sample_3", resume=False, progress=False)
        assert signal.getsignal(signum) == default                  # handler restored
    finally:
        signal.signal(signum, outer)
    _, meta = io.load_checkpoint(tmp_path / "sample_3" / "checkpoint.h5")
    assert meta["step"] == 37
    monkeypatch.setattr(Simulation, "step", real_step)
    runner.run_sample(scn, 3, tmp_path / "sample_3", resume=True, progress=False)
    one = io.read_series(out / "sample_3" / "shear_series.h5")
    two = io.read_series(tmp_path / "sample_3" / "shear_series.h5")
    for key in ("displacement", "shear_stress", "bonds_intact"):
        assert np.array_equal(one[key], two[key]), key


@pytest.mark.parametrize("stage", ["prepare", "shear"])
def test_a_resumed_run_writes_its_series_csv_with_the_columns_in_their_order(micro_run, tmp_path,
                                                                          monkeypatch, stage):
    """A checkpoint's series come back from HDF5 sorted by name: a run interrupted in a stage
    and resumed wrote that stage's CSV with its columns by name (bonds_broken_shear first,
    time eighth; session 47's audit of kills and resumes). The checkpoint records their order:
    the resumed run's series files are those of the uninterrupted run, byte for byte."""
    from tcd import config, runner
    from tcd.simulation import Simulation
    scenario, out = micro_run
    text = MICRO.replace("checkpoint_every_s = 0.5", "checkpoint_every_s = 1e6")
    scn = config.parse_scenario(text, "<micro>")
    whole = json.loads((out / "sample_3" / "summary.json").read_text())
    at = 37 if stage == "prepare" else whole["stages"]["0:prepare"]["steps"] + 25
    real_step, calls = Simulation.step, {"n": 0}

    def step_then_ctrl_c(self, count=1):
        calls["n"] += 1
        if calls["n"] == at:
            os.kill(os.getpid(), signal.SIGINT)
        return real_step(self, count)
    monkeypatch.setattr(Simulation, "step", step_then_ctrl_c)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            runner.run_sample(scn, 3, tmp_path / "sample_3", resume=False, progress=False)
    finally:
        signal.signal(signal.SIGINT, outer)
    _, meta = io.load_checkpoint(tmp_path / "sample_3" / "checkpoint.h5")
    assert scn.stages[meta["stage"]].kind == stage and meta["step_in_phase"] > 0
    monkeypatch.setattr(Simulation, "step", real_step)
    runner.run_sample(scn, 3, tmp_path / "sample_3", resume=True, progress=False)
    for kind in ("prepare", "shear"):
        name = f"{kind}_series.csv"
        resumed = (tmp_path / "sample_3" / name).read_text()
        assert resumed.startswith("time [s],step [1],sweeps [1],"), (name, resumed[:80])
        assert resumed == (out / "sample_3" / name).read_text(), name
        a = io.read_series(out / "sample_3" / f"{kind}_series.h5")
        b = io.read_series(tmp_path / "sample_3" / f"{kind}_series.h5")
        assert list(a) == list(b)
        for key in a:
            assert np.array_equal(a[key], b[key], equal_nan=a[key].dtype.kind == "f"), (kind, key)


def test_sigterm_to_a_parallel_run_is_passed_on_to_its_workers(tmp_path):
    """With --jobs N the samples run in worker processes: a SIGTERM to the parent is sent on to
    every worker (each then checkpoints at the end of its step and stops) and the parent
    carries on waiting for them, instead of dying and leaving them to run on their own."""
    from tcd import runner

    class Pool:                    # what ForwardTerm reads of a ProcessPoolExecutor
        _processes = {}
    worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"],
                              preexec_fn=default_stop_signals)
    Pool._processes = {worker.pid: worker}
    outer = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        with runner.ForwardTerm(Pool()):
            os.kill(os.getpid(), signal.SIGTERM)      # this process survives it ...
            assert worker.wait(timeout=30) == -signal.SIGTERM       # ... its worker gets it
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL   # handler restored
    finally:
        signal.signal(signal.SIGTERM, outer)
        if worker.poll() is None:
            worker.kill()


def _interrupt_after(checks: int):
    """A runner.DeferredInterrupt whose interrupt is pending from its (checks + 1)-th check
    on: the run stops there as after a Ctrl-C, at the end of a step."""
    from tcd import runner

    class StopAfter(runner.DeferredInterrupt):
        seen = 0

        @property
        def pending(self):
            StopAfter.seen += 1
            return StopAfter.seen > checks

        @pending.setter
        def pending(self, value):
            pass
    return StopAfter


def _shear_only(prepared, seeds="[3]"):
    # the serial schedule on every backend: a batch gives each sample's numbers bit for bit
    # there (the coloured schedule, the GPU's default, colours and converges the batch as one)
    head = MICRO[:MICRO.index('[[stage]]\nkind = "prepare"')].replace("seeds = [3]", f"seeds = {seeds}")
    head = head.replace("[solver]\n", '[solver]\nschedule = "serial"\n', 1)
    shear = MICRO[MICRO.index('[[stage]]\nkind = "shear"'):]
    return head + shear.replace('kind = "shear"', f'kind = "shear"\nsample = "{prepared}"', 1)


def test_batched_shear_equals_the_samples_sheared_one_by_one(micro_run, tmp_path, monkeypatch,
                                                             capsys):
    """`tcd run --batch`: two samples (seeds 3 and 4, both from seed 3's prepared file) sheared
    as one batched simulation give, each, exactly the series of the unbatched shear; a batch
    interrupted mid-way resumes from its checkpoint to the same end, its series CSV included; a scenario with a
    preparation stage is refused with a message that says why."""
    from tcd import runner
    _, out = micro_run
    prepared = (out / "sample_3" / "prepared.h5").as_posix()
    single = tmp_path / "single.toml"
    single.write_text(_shear_only(prepared))
    assert run_tcd(["run", str(single), "--out", str(tmp_path / "one")]) == 0
    pair = tmp_path / "pair.toml"
    pair.write_text(_shear_only(prepared, "[3, 4]"))
    assert run_tcd(["run", str(pair), "--out", str(tmp_path / "batch"), "--batch"]) == 0
    one = io.read_series(tmp_path / "one" / "sample_3" / "shear_series.h5")
    for seed in (3, 4):
        got = io.read_series(tmp_path / "batch" / f"sample_{seed}" / "shear_series.h5")
        assert len(got["shear_stress"]) == len(one["shear_stress"]) > 10
        for key in ("displacement", "shear_stress", "sweeps", "residual", "contacts",
                    "bonds_intact", "kinetic_energy"):
            assert np.array_equal(one[key], got[key]), (seed, key)
    a = json.loads((tmp_path / "one" / "sample_3" / "summary.json").read_text())
    summary = json.loads((tmp_path / "batch" / "summary.json").read_text())
    assert summary["batched"] and [s["seed"] for s in summary["samples"]] == [3, 4]
    for s in summary["samples"]:
        assert s["tau_peak_MPa"] == a["tau_peak_MPa"] and s["bonds_total"] == a["bonds_total"] > 0
        assert s["inputs"] == a["inputs"] == {"0:shear": io.file_record(prepared)}
    frames = io.read_frame(tmp_path / "batch" / "sample_4" / "states.h5", -1)
    final = io.read_frame(tmp_path / "one" / "sample_3" / "states.h5", -1)
    assert np.array_equal(frames["particles/x"], final["particles/x"])
    # a shear from the saved sample writes the frames of the same shear inside the full run
    # (it wrote one more, at its first step; so did every stage of a run: session 48's audit)
    import h5py

    def frame_times(path, stage):
        with h5py.File(path, "r") as f:
            return [float(f["frames"][k].attrs["time"]) for k in sorted(f["frames"], key=int)
                    if f["frames"][k].attrs["stage"] == stage]
    full = frame_times(out / "sample_3" / "states.h5", "shear")
    assert frame_times(tmp_path / "one" / "sample_3" / "states.h5", "shear") == full
    assert frame_times(tmp_path / "batch" / "sample_3" / "states.h5", "shear") == full
    prep = frame_times(out / "sample_3" / "states.h5", "prepare")
    assert prep[0] == 0.0 and prep[1] == pytest.approx(0.05, abs=1e-9), prep[:3]
    assert full[1] - full[0] > 5 * 5e-4, full[:3]

    # a finished batch keeps its checkpoint: `tcd info` said it "stopped in the shear"
    finished = runner.run_info(tmp_path / "batch")
    assert "batch: done (its last checkpoint: batch_checkpoint.h5)" in finished, finished
    monkeypatch.setattr(runner, "DeferredInterrupt", _interrupt_after(15))
    with pytest.raises(KeyboardInterrupt):
        runner.run_batch(load_here(pair), tmp_path / "cut", progress=False)
    assert (tmp_path / "cut" / "batch_checkpoint.h5").exists()
    assert not (tmp_path / "cut" / "summary.json").exists()
    _, meta = io.load_checkpoint(tmp_path / "cut" / "batch_checkpoint.h5")
    info = runner.run_info(tmp_path / "cut")            # `tcd info RUN_DIR`
    assert f"--out {tmp_path / 'cut'} --batch --resume`)" in info, info
    assert (f"batch: stopped in the shear of seeds 3, 4, phase {meta['phases'][0]['name']!r} at "
            f"step {meta['step_in_phase']} of {meta['phases'][0]['steps']}, t = ") in info, info
    arrays, _ = io.load_checkpoint(tmp_path / "cut" / "batch_checkpoint.h5")
    window = load_here(pair).stages[0].smoothing_window_mm * 1e-3
    for seed in (3, 4):     # each sample's travel, stress and peak so far, from its series
        d = arrays[f"series/{seed}/displacement"]
        tau = arrays[f"series/{seed}/shear_stress"]
        peak, at, _ = obs.peak_of(d, tau, window)
        assert (f"sample_{seed}: in the batch (above); the ring at {d[-1] * 1e3:.3f} mm, "
                f"{tau[-1] / 1e6:.4g} MPa, peak so far {peak / 1e6:.4g} MPa at {at * 1e3:.3g} "
                "mm\n") in info, info
    # `tcd compare` on the batch under way: each sample's curve so far, from the batch's checkpoint
    from tcd import figures
    _, so_far = figures.load_run(tmp_path / "cut", stopped=True)
    assert sorted((s.seed, s.stopped) for s in so_far) == [("3", True), ("4", True)]
    for s in so_far:
        assert np.array_equal(s.stress, arrays[f"series/{s.seed}/shear_stress"]), s.seed
        assert s.window == pytest.approx(window)
    with pytest.raises(ValueError, match=r"no sample 5 in the batch of seeds \[3, 4\]"):
        io.checkpoint_shear_series(tmp_path / "cut" / "batch_checkpoint.h5", 5)
    monkeypatch.undo()
    assert run_tcd(["run", str(pair), "--out", str(tmp_path / "cut"), "--batch", "--resume"]) == 0
    resumed = json.loads((tmp_path / "cut" / "summary.json").read_text())
    assert [s["inputs"] for s in resumed["samples"]] == [a["inputs"]] * 2   # through the resume
    for seed in (3, 4):
        got = io.read_series(tmp_path / "cut" / f"sample_{seed}" / "shear_series.h5")
        assert np.array_equal(one["shear_stress"], got["shear_stress"]), seed
        assert np.array_equal(one["time"], got["time"]), seed
        # the CSV's columns in their order, as the uninterrupted batch's (session 47)
        name = f"sample_{seed}/shear_series.csv"
        assert (tmp_path / "cut" / name).read_text() == (tmp_path / "batch" / name).read_text(), seed

    # stopped while the batch was built (SIGTERM before its first checkpoint): --resume
    # refused it ("nothing to resume") and a new run was refused too; now it starts over
    def stopped(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(runner, "plan_shears", stopped)
    with pytest.raises(KeyboardInterrupt):
        runner.run_batch(load_here(pair), tmp_path / "early", progress=False)
    monkeypatch.undo()
    assert (tmp_path / "early" / "scenario.toml").is_file()
    assert not (tmp_path / "early" / "batch_checkpoint.h5").exists()
    assert run_tcd(["run", str(pair), "--out", str(tmp_path / "early"), "--batch", "--resume"]) == 0
    assert "no batch checkpoint yet" in capsys.readouterr().err
    for seed in (3, 4):
        name = f"sample_{seed}/shear_series.csv"
        assert (tmp_path / "early" / name).read_text() == (tmp_path / "batch" / name).read_text()

    scenario, _ = micro_run
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "no"), "--batch"]) == 2


def test_renumbered_shear_traces_its_particles_and_resumes_bit_for_bit(micro_run, tmp_path,
                                                                       monkeypatch):
    """`renumber = true`: the shear numbers the sample's particles along x before bonding.
    Its states keep each particle's index in the prepared sample (particles/sample_index),
    the bonds are the same, the curve agrees with the shear as numbered in the sample up to
    the solver's tolerance, and a run interrupted mid-shear resumes to the same end bit for
    bit (the resumed run does not renumber again)."""
    from tcd import runner
    _, out = micro_run
    prepared = out / "sample_3" / "prepared.h5"
    plain = tmp_path / "plain.toml"
    plain.write_text(_shear_only(prepared.as_posix()))
    text = _shear_only(prepared.as_posix()).replace('kind = "shear"', 'kind = "shear"\nrenumber = true', 1)
    text = text.replace("checkpoint_every_s = 0.5", "checkpoint_every_s = 1e6")
    renum = tmp_path / "renum.toml"
    renum.write_text(text)
    assert run_tcd(["run", str(plain), "--out", str(tmp_path / "plain")]) == 0
    assert run_tcd(["run", str(renum), "--out", str(tmp_path / "renum")]) == 0
    sample, _ = io.load_checkpoint(prepared)
    first = io.read_frame(tmp_path / "renum" / "sample_3" / "states.h5", 0)
    index = first["particles/sample_index"]
    assert not np.array_equal(index, np.arange(len(index)))
    np.testing.assert_array_equal(first["particles/x"], sample["particles/x"][index])
    np.testing.assert_array_equal(first["particles/radius"], sample["particles/radius"][index])
    assert np.all(np.diff(first["particles/x"][:, 0]) >= 0)          # numbered along x
    last = io.read_frame(tmp_path / "renum" / "sample_3" / "states.h5", -1)
    np.testing.assert_array_equal(last["particles/sample_index"], index)
    a = json.loads((tmp_path / "plain" / "sample_3" / "summary.json").read_text())
    b = json.loads((tmp_path / "renum" / "sample_3" / "summary.json").read_text())
    assert a["bonds_total"] == b["bonds_total"] > 0
    one = io.read_series(tmp_path / "plain" / "sample_3" / "shear_series.h5")
    two = io.read_series(tmp_path / "renum" / "sample_3" / "shear_series.h5")
    assert len(one["shear_stress"]) == len(two["shear_stress"]) > 10
    assert not np.array_equal(one["shear_stress"], two["shear_stress"])   # another order
    peak = np.abs(one["shear_stress"]).max()
    early = slice(0, len(one["shear_stress"]) // 2)
    np.testing.assert_allclose(two["shear_stress"][early], one["shear_stress"][early], atol=0.05 * peak)

    # interrupted mid-shear, then resumed: the same end as the uninterrupted renumbered run
    monkeypatch.setattr(runner, "DeferredInterrupt", _interrupt_after(20))
    with pytest.raises(KeyboardInterrupt):
        runner.run_sample(load_here(renum), 3, tmp_path / "cut" / "sample_3",
                          resume=False, progress=False)
    monkeypatch.undo()
    _, meta = io.load_checkpoint(tmp_path / "cut" / "sample_3" / "checkpoint.h5")
    assert 0 < meta["step"]
    runner.run_sample(load_here(renum), 3, tmp_path / "cut" / "sample_3", resume=True,
                      progress=False)
    got = io.read_series(tmp_path / "cut" / "sample_3" / "shear_series.h5")
    for key in ("displacement", "shear_stress", "sweeps", "bonds_intact"):
        assert np.array_equal(two[key], got[key]), key
    end = io.read_frame(tmp_path / "cut" / "sample_3" / "states.h5", -1)
    np.testing.assert_array_equal(end["particles/x"], last["particles/x"])
    np.testing.assert_array_equal(end["particles/sample_index"], index)


def test_progress_after_a_resume_counts_only_the_new_steps(capsys, monkeypatch):
    """A phase resumed at step 5000 of 15000 that then makes 100 steps in 10 s runs at
    10 steps/s with 16.5 min left (not 510 steps/s and 0.3 min)."""
    from tcd import runner
    clock = iter([0.0, 0.0, 10.0])
    monkeypatch.setattr(runner.time, "perf_counter", lambda: next(clock))
    bar = runner.Progress(True, "seed 1 shear:shear", 15000, 2e-4)
    bar.update(5000, 4.44)          # the resumed step
    bar.update(5100, 4.46)
    line = capsys.readouterr().err
    assert "step 5100/15000" in line and "10.0 steps/s" in line and "16.5 min left" in line


def test_progress_lines_give_the_rate_and_sweeps_since_the_line_before(capsys, monkeypatch):
    """The rate since the start includes the compiling; from its second line on, a log line
    also gives the rate and the mean sweeps per step since the line before: 100 steps in 30 s
    at 10 then 30 sweeps."""
    from tcd import runner
    clock = iter([0.0, 0.0, 10.0, 40.0])
    monkeypatch.setattr(runner.time, "perf_counter", lambda: next(clock))
    bar = runner.Progress(True, "batch of 5 shear", 15000, 2e-4)
    bar.update(0, 3.48)
    for _ in range(100):
        bar.count_sweeps(50)
    bar.update(100, 3.50, "sweeps=50")
    first = capsys.readouterr().err
    assert "10.0 steps/s, 24.8 min left at the mean rate sweeps=50" in first
    assert "over the last" not in first and "last lines' rate" not in first
    for k in range(100):
        bar.count_sweeps(10 if k < 50 else 30)
    bar.update(200, 3.52, "sweeps=30")
    line = capsys.readouterr().err
    assert "5.0 steps/s (3.3 over the last 100 steps, 20.0 sweeps per step)" in line
    # the time left at both rates: 14800 steps at 5 and at 3.3 steps per second
    assert "49.3 min left at the mean rate, 74.0 at the last lines' rate sweeps=30" in line


def test_jobs_that_would_share_cores_between_partitioned_threads_are_refused(tmp_path, monkeypatch):
    """Two samples at once, two partitioned threads each, on two cores: refused before anything
    runs or is written, with the way out named."""
    from tcd import runner
    from tcd.config import parse_scenario
    text = (ROOT / "scenarios" / "tiny.toml").read_text()
    text = text.replace("seeds = [1]", "seeds = [1, 2]").replace(
        "[solver]\n", '[solver]\nschedule = "partitioned"\nthreads = 2\n', 1)
    scn = parse_scenario(text, "tiny-partitioned")
    monkeypatch.setattr(runner.os, "cpu_count", lambda: 2)
    with pytest.raises(ValueError, match=r"4 solver threads on 2 cores.*use --jobs 1"):
        runner.run_scenario(scn, tmp_path / "out", jobs=2, progress=False)
    assert not (tmp_path / "out").exists()


def test_resume_refuses_a_scenario_or_backend_other_than_the_run_started_with(micro_run, tmp_path,
                                                                               capsys):
    """A resumed run must continue the configuration it started with: a changed physical
    setting or precision is refused before anything is written; the same scenario with other
    comments, or from another file, resumes (here: a finished run, which resumes at once)."""
    import shutil
    _, out = micro_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    changed = tmp_path / "changed.toml"
    changed.write_text(MICRO.replace("max_sweeps = 500", "max_sweeps = 500\n[material]\nfriction = 0.3"))
    assert run_tcd(["run", str(changed), "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "--resume with a scenario other than the one this run started with" in err
    assert "material.friction: 0.7 -> 0.3" in err
    same = tmp_path / "same.toml"
    same.write_text("# a comment\n" + MICRO)
    mine = backend.precision()
    other = "f32" if mine == "f64" else "f64"
    assert run_tcd(["run", str(same), "--out", str(run), "--resume", "--precision", other]) == 2
    assert f"backend.precision: '{mine}' -> '{other}'" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    # damaged records are named as such (session 42 audit: a malformed scenario.toml was
    # reported under the new scenario's name; an unreadable run.json as a fast-math change)
    for name, damage, message in (("scenario.toml", "[solver\n", "scenario.toml: the scenario this "
                                   "run started with cannot be read back (line 1, column 8: "
                                   "malformed TOML"),
                                  ("run.json", "{", "run.json: the backend this run started with "
                                   "cannot be read back")):
        kept = (run / name).read_bytes()
        (run / name).write_text(damage)
        assert run_tcd(["run", str(same), "--out", str(run), "--resume"]) == 2, name
        err = capsys.readouterr().err
        assert message in err and "fast_math" not in err, (name, err)
        (run / name).write_bytes(kept)
    assert run_tcd(["run", str(same), "--out", str(run), "--resume"]) == 0
    assert (run / "scenario.toml").read_text() == MICRO       # the record is the first one


def test_resume_refuses_another_fast_math_setting(micro_run, tmp_path, capsys, monkeypatch):
    """Taichi's fast math changes the numbers' last bits: run.json records it, and a resumed run
    with the other setting is refused, naming TCD_FAST_MATH. A run from before the record (no
    key) had it on, unless TCD_FAST_MATH says otherwise now."""
    import shutil
    _, out = micro_run
    now = backend.fast_math_setting("cpu")
    assert json.loads((out / "run.json").read_text())["fast_math"] is now
    run = tmp_path / "run"
    shutil.copytree(out, run)
    record = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**record, "fast_math": not now}))
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert run_tcd(["run", str(out / "scenario.toml"), "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"backend.fast_math: {not now!r} -> {now!r}" in err
    assert f"TCD_FAST_MATH={int(not now)}" in err
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    del record["fast_math"]                     # a run started before session 33
    (run / "run.json").write_text(json.dumps(record))
    monkeypatch.delenv(backend.FAST_MATH_ENV, raising=False)
    code = run_tcd(["run", str(out / "scenario.toml"), "--out", str(run), "--resume"])
    if now:
        assert code == 0
    else:
        assert code == 2 and "predates the record" in capsys.readouterr().err
        monkeypatch.setenv(backend.FAST_MATH_ENV, "0")      # the user says how it started
        assert run_tcd(["run", str(out / "scenario.toml"), "--out", str(run), "--resume"]) == 0


def test_run_into_a_file_is_refused_before_anything_is_written(tmp_path, capsys):
    target = tmp_path / "taken.png"
    target.write_bytes(b"an image")
    scenario = tmp_path / "micro.toml"
    scenario.write_text(MICRO)
    assert run_tcd(["run", str(scenario), "--out", str(target)]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err
    assert target.read_bytes() == b"an image"


def test_an_output_the_file_system_refuses_is_a_one_line_error(tmp_path, capsys):
    """An OSError on an output (a folder under a file here; a read-only or full disk, a name
    too long) was a Python traceback (session 42 audit): now one line naming the path."""
    blocker = tmp_path / "afile"
    blocker.write_text("a file")
    scenario = tmp_path / "micro.toml"
    scenario.write_text(MICRO)
    assert run_tcd(["run", str(scenario), "--out", str(blocker / "out")]) == 74
    err = capsys.readouterr().err
    assert err.startswith("tcd: error: ") and "Traceback" not in err
    assert str(blocker) in err and "run it again" in err
    assert blocker.read_text() == "a file"


def _frame_times(path):
    return [io.read_frame(path, k)["time"] for k in range(io.frame_count(path))]


def test_resume_after_a_hard_kill_cuts_the_frames_written_after_the_checkpoint(micro_run, tmp_path,
                                                                              monkeypatch, capsys):
    """A run killed hard (SIGKILL, a power cut) after writing frames past its last checkpoint
    wrote them again when resumed: states.h5 held frames twice, its time running backwards
    (session 42 audit). The checkpoint now records the frames written; a resume cuts the file
    back to them, and the run ends with the frames of an uninterrupted one. A resume whose
    checkpoint is not this run's, or whose states file or scenario record went missing, is
    refused with the file named."""
    import shutil
    from tcd.simulation import Simulation
    _, out = micro_run
    text = _shear_only((out / "sample_3" / "prepared.h5").as_posix())
    text = text.replace("snapshot_every = 0.05", "snapshot_every = 0.002")
    text = text.replace("checkpoint_every_s = 0.5", "checkpoint_every_s = 1e6")
    scenario = tmp_path / "shear.toml"
    scenario.write_text(text)
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "whole")]) == 0
    whole = _frame_times(tmp_path / "whole" / "sample_3" / "states.h5")
    assert len(whole) > 6
    # the snapshot of the shear's last step is its last frame, once (session 44: a snapshot
    # interval ending with the stage wrote it twice)
    assert all(b > a for a, b in zip(whole, whole[1:])), whole

    real_step, calls = Simulation.step, {"n": 0}

    def step_then_ctrl_c(self, count=1):
        calls["n"] += 1
        if calls["n"] == 15:
            os.kill(os.getpid(), signal.SIGINT)
        return real_step(self, count)
    monkeypatch.setattr(Simulation, "step", step_then_ctrl_c)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "cut")]) == 130
    finally:
        signal.signal(signal.SIGINT, outer)
    monkeypatch.setattr(Simulation, "step", real_step)
    cut = tmp_path / "cut"
    shutil.copytree(cut, tmp_path / "pristine")
    states = cut / "sample_3" / "states.h5"
    _, meta = io.load_checkpoint(cut / "sample_3" / "checkpoint.h5")
    assert meta["frames"] == io.frame_count(states) and meta["seed"] == 3
    # what a hard kill leaves: frames of later steps, past the checkpoint
    last = {k: v for k, v in io.read_frame(states, -1).items() if k not in ("time", "step", "stage")}
    for k in (1, 2):
        io.append_frame(states, last, time=meta["time"] + k * 0.002, step=meta["step"] + 4 * k,
                        stage="shear")
    capsys.readouterr()
    assert run_tcd(["run", str(scenario), "--out", str(cut), "--resume"]) == 0
    assert "2 frame(s) written after the last checkpoint were dropped" in capsys.readouterr().err
    assert _frame_times(states) == whole
    a = io.read_series(tmp_path / "whole" / "sample_3" / "shear_series.h5")
    b = io.read_series(cut / "sample_3" / "shear_series.h5")
    assert np.array_equal(a["shear_stress"], b["shear_stress"])

    def refused(name, spoil, message):
        run = tmp_path / name
        shutil.copytree(tmp_path / "pristine", run)
        spoil(run)
        capsys.readouterr()
        assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 2, name
        err = capsys.readouterr().err
        assert __import__("re").search(message, err), (name, err)
        assert not (run / "summary.json").exists(), name

    refused("no_states", lambda run: (run / "sample_3" / "states.h5").unlink(),
            r"states.h5: 0 frames, but the checkpoint .* was written after frame \d+")
    refused("a_sample", lambda run: shutil.copy(out / "sample_3" / "prepared.h5",
                                                run / "sample_3" / "checkpoint.h5"),
            r"checkpoint.h5: not a checkpoint of a tcd run \(its meta lacks stage")
    refused("no_record", lambda run: (run / "scenario.toml").unlink(),
            r"scenario.toml is missing")

    def foreign(run):
        ck = run / "sample_3" / "checkpoint.h5"
        arrays, meta = io.load_checkpoint(ck)
        meta["scenario_text"] = meta["scenario_text"].replace("[solver]\n", "[material]\nfriction = 0.3\n[solver]\n", 1)
        io.save_checkpoint(ck, arrays, meta)
    refused("foreign", foreign, r"checkpoint.h5: written by a run of another scenario: "
                                r"material.friction: 0.3 -> 0.7")


def test_a_shear_starts_only_from_an_unbonded_prepared_sample(micro_run, tmp_path):
    """A finished run's checkpoint.h5 (after its shear) was accepted as a prepared sample and
    sheared a second time."""
    from tcd import runner
    from tcd.config import load_scenario
    scenario, out = micro_run
    scn = load_scenario(scenario)
    with pytest.raises(ValueError, match="a run checkpoint .*not a prepared sample"):
        runner.load_prepared(scn, out / "sample_3" / "checkpoint.h5")
    arrays, meta = io.load_checkpoint(out / "sample_3" / "checkpoint.h5")
    assert len(arrays["bonds/state"]) > 0
    _, prepared_meta = io.load_checkpoint(out / "sample_3" / "prepared.h5")
    io.save_checkpoint(tmp_path / "sheared.h5", arrays, prepared_meta)
    with pytest.raises(ValueError, match="bonds: it was sheared already"):
        runner.load_prepared(scn, tmp_path / "sheared.h5")
    sim = runner.load_prepared(scn, out / "sample_3" / "prepared.h5")
    assert sim.n == len(arrays["particles/radius"])
    sim.close()


def test_shear_benchmark_on_a_prepared_sample_reports_phases_and_a_trace(micro_run, tmp_path,
                                                                      on_backend):
    """`tcd bench shear --sample FILE --trace CSV` on the micro run's prepared sample: the
    figures of the loop, its ten phases adding up to it, one trace row per timed step."""
    from tcd import bench
    _, out = micro_run
    trace = tmp_path / "shear.csv"
    res = bench.shear(time=0.004, sample=str(out / "sample_3" / "prepared.h5"), trace=str(trace),
                      **on_backend)
    assert res["particles"] == 80 and res["steps"] == 20 and res["bonds"] > 0
    assert res["seconds_per_particle_step"] > 0
    ph = res["phases"]
    assert len(ph) == 10 and sum(p["steps"] for p in ph) == 20 - bench.WARMUP_STEPS == 18
    rows = list(csv.DictReader(open(trace)))
    assert len(rows) == 18
    # the phases share out the timed steps' walls (rounded to 1 us each), which the loop's
    # wall holds (a comparison with the loop's own wall at 5 % failed on a busy machine: a
    # preemption after the last step's clock is a large part of an 18-step loop of 80 grains)
    steps_wall = sum(float(r["wall_s"]) for r in rows)
    assert sum(p["wall_s"] for p in ph) == pytest.approx(steps_wall, abs=2e-5)
    assert res["loop_wall_s"] >= steps_wall - 2e-5
    assert np.mean([int(r["sweeps"]) for r in rows]) == pytest.approx(res["mean_sweeps"])
    assert float(rows[-1]["residual"]) == pytest.approx(res["final_residual"], rel=1e-5)


def test_every_seeds_sample_is_checked_before_the_first_seed_runs(micro_run, tmp_path, capsys):
    """A five-seed shear study whose last sample file is bad stopped after hours, when that
    seed's turn came; now every seed's file is read and checked before anything runs."""
    _, out = micro_run
    good = out / "sample_3" / "prepared.h5"
    import shutil
    shutil.copy(good, tmp_path / "s_3.h5")
    arrays, meta = io.load_checkpoint(good)
    f64 = arrays["particles/inv_mass"].dtype == np.float64
    cases = {
        "not_tcd": (None, "missing schema_version attribute"),
        "no_radius": ({k: v for k, v in arrays.items() if k != "particles/radius"},
                      "not a prepared sample: it lacks particles/radius"),
        "short_x": ({**arrays, "particles/x": arrays["particles/x"][:-1]},
                    r"key 'particles/\w+' has length \d+ but 'particles/\w+' has \d+"),
        "negative_radius": ({**arrays, "particles/radius": -arrays["particles/radius"]},
                            r"'particles/radius' holds \d+ radii that are not positive and finite"),
        "nan_velocity": ({**arrays, "particles/v": arrays["particles/v"] * np.nan},
                         r"particles/v must be finite \(got NaN or infinity at particle 0\)"),
        "short_f_ext": ({**arrays, "particles/f_ext": arrays["particles/f_ext"][:-1]},
                        r"particles/f_ext has shape \(\d+, 3\) and dtype float(32|64), expected "
                        r"\(\d+, 3\) numbers"),
        # what only a simulation's load checked (session 44: seed 3 ran before seed 4's
        # negative inverse masses were found)
        "negative_inv_mass": ({**arrays, "particles/inv_mass": -arrays["particles/inv_mass"]},
                              r"particles/inv_mass holds values below 0.0"),
        # the shear runs with the sample's own masses (session 47's fuzz: an inverse mass of
        # 1e300 ran to NaN; masses of another density than the scenario's went unnoticed)
        # (an f32 sample cannot hold 1e300: 1e30 there)
        "absurd_inv_mass": ({**arrays, "particles/inv_mass": np.full_like(
                                arrays["particles/inv_mass"], 1e300 if f64 else 1e30)},
                            r"masses \(particles/inv_mass and radius\) are those of a density "
                            r"of [0-9.e+-]+ to [0-9.e+-]+ kg/m\^3, and the scenario's \[material\] "
                            r"density is 2600"),
        "other_density": ({**arrays, "particles/inv_mass": arrays["particles/inv_mass"] * 1.01,
                           "particles/inv_inertia": arrays["particles/inv_inertia"] * 1.01},
                          r"those of a density of 2574.26 kg/m\^3, and the scenario's "
                          r"\[material\] density is 2600"),
        "not_spheres": ({**arrays, "particles/inv_inertia": arrays["particles/inv_inertia"] * 0.6},
                        r"\d+ grain\(s\) have a moment of inertia \(particles/inv_inertia\) "
                        r"other than a solid sphere's 2/5 m r\^2"),
        "negative_layer": ({**arrays, "particles/layer": arrays["particles/layer"] - 5},
                           r"particles/layer holds values below 0"),
        "bad_contact": ({**arrays, "contacts/i": arrays["contacts/i"] + len(arrays["particles/x"])},
                        r"key 'contacts/i' has indices in \[\d+, \d+\], expected \[0, \d+\)"),
        # what the shear's plan needs of the walls (session 42 audit: these stopped the study
        # when that seed's turn came, one with a NumPy message naming neither file nor seed)
        "no_mould": (arrays, r"\(seed 4\): the sample has no cylindrical mould",
                     {**meta, "walls": [w for w in meta["walls"] if w["kind"] != "cylinder"]}),
        "narrow_mould": (arrays, r"\(seed 4\): shear displacement_mm 0.2 mm is not smaller than "
                                 r"the sample's 0.2 mm diameter",
                         {**meta, "walls": [{**w, "radius": 1e-4} if w["kind"] == "cylinder" else w
                                            for w in meta["walls"]]}),
    }
    for name, (bad, message, *bad_meta) in cases.items():
        path = tmp_path / "s_4.h5"
        path.unlink(missing_ok=True)
        if bad is None:
            import h5py
            with h5py.File(path, "w") as f:
                f["x"] = np.zeros(3)
        else:
            io.save_checkpoint(path, bad, bad_meta[0] if bad_meta else meta)
        scenario = tmp_path / f"{name}.toml"
        scenario.write_text(_shear_only((tmp_path / "s_{seed}.h5").as_posix(), "[3, 4]"))
        run_dir = tmp_path / f"run_{name}"
        assert run_tcd(["run", str(scenario), "--out", str(run_dir)]) == 2, name
        err = capsys.readouterr().err
        assert str(path) in err and __import__("re").search(message, err), (name, err)
        assert not run_dir.exists(), name           # nothing ran, nothing was written


def test_a_run_refused_while_its_sample_is_built_takes_back_its_records(micro_run, tmp_path,
                                                                         capsys):
    """Two grains at one centre pass the sample's checks and are refused when its simulation
    is built, after the run wrote its records: the refusal used to leave run.json,
    scenario.toml and an empty sample folder (session 47's fuzz). Now a new --out directory is
    gone again, one that existed is left as it was, and a run that wrote results keeps all."""
    _, out = micro_run
    arrays, meta = io.load_checkpoint(out / "sample_3" / "prepared.h5")
    x = np.array(arrays["particles/x"])
    x[1] = x[0]
    io.save_checkpoint(tmp_path / "s_3.h5", {**arrays, "particles/x": x}, meta)
    scenario = tmp_path / "same_centre.toml"
    scenario.write_text(_shear_only((tmp_path / "s_{seed}.h5").as_posix()))
    new = tmp_path / "new_run"
    assert run_tcd(["run", str(scenario), "--out", str(new)]) == 2
    err = capsys.readouterr().err
    assert "particles 0 and 1 have the same centre" in err and "s_3.h5" in err, err
    assert not new.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    (kept / "sample_3").mkdir()
    assert run_tcd(["run", str(scenario), "--out", str(kept)]) == 2
    assert sorted(p.name for p in kept.rglob("*")) == ["notes.txt", "sample_3"]
    from tcd import runner
    from tcd.config import load_scenario
    results = tmp_path / "results"
    with pytest.raises(RuntimeError):
        with runner.recorded_run(load_scenario(scenario), results, False):
            (results / "sample_3").mkdir()
            (results / "sample_3" / "states.h5").write_bytes(b"frames")
            raise RuntimeError("a sample failed after writing")
    assert sorted(p.name for p in results.rglob("*")) == [
        ".tcd.lock", "run.json", "sample_3", "scenario.toml", "states.h5"]


def test_a_series_ends_where_its_phase_ended_whatever_series_every(micro_run, tmp_path):
    """series_every larger than the shear's steps crashed after the shear had run (its series
    was empty), and the summary's step count was the records times series_every."""
    _, out = micro_run
    text = _shear_only((out / "sample_3" / "prepared.h5").as_posix())
    text = text.replace("[output]\n", "[output]\nseries_every = 7\n", 1)
    text = text.replace("displacement_mm = 0.2", "displacement_mm = 0.03")
    scenario = tmp_path / "sparse.toml"
    scenario.write_text(text)
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "sparse")]) == 0
    s = io.read_series(tmp_path / "sparse" / "sample_3" / "shear_series.h5")
    steps = int(round(0.03e-3 / (600e-3 / 60) / 5e-4))            # 6 steps of 5e-4 s
    summary = json.loads((tmp_path / "sparse" / "sample_3" / "summary.json").read_text())
    assert summary["stages"]["0:shear"]["steps"] == steps
    assert len(s["time"]) == 1 and np.asarray(s["step"])[-1] - np.asarray(s["step"])[0] == 0
    assert np.asarray(s["displacement"])[-1] == pytest.approx(0.03e-3, rel=1e-9)


def test_preparation_shortfalls_are_named():
    """A pour or hold stopped by its time limit, a course's plate above its target, a sample
    taller than asked: each is a sentence of summary.json's `warnings` (and printed)."""
    from tcd.config import parse_scenario
    from tcd.protocols import Prepare
    scn = parse_scenario(MICRO)
    proto = Prepare(scn.stages[0], scn, 3)
    phases = [{"phase": "pour", "layer": 0, "steps": 600, "settled": False},
              {"phase": "hold", "layer": 0, "steps": 50, "settled": True, "target": 4e-3,
               "plate_mm": 4.03},                       # within 1 % of the 4 mm course
              {"phase": "pour", "layer": 1, "steps": 300, "settled": True},
              {"phase": "hold", "layer": 1, "steps": 200, "settled": False, "target": 8e-3,
               "plate_mm": 8.5}]
    found = proto.shortfalls(phases, 8.5)
    assert len(found) == 4
    assert "pour of course 0 (binder) reached its time limit (600 steps)" in found[0]
    assert "hold of course 1 (surface) reached its time limit" in found[1]
    assert "course 1 (surface): its plate stopped at 8.50 mm, above its target 8.00 mm" in found[2]
    assert "the sample is 8.50 mm high, above sample_height_mm (8 mm)" in found[3]
    # records of runs before `settled` was kept say nothing either way
    assert proto.shortfalls([{"phase": "pour", "layer": 0, "steps": 600}], 8.0) == []
    # the invariants a diverged run breaks first (session 42: gravity 1e30 exited quietly)
    assert proto.shortfalls([], 8.0, 0.0099, 0) == []
    found = proto.shortfalls([], 8.0, 2.51, 4)
    assert "the largest overlap is 251 % of the smallest diameter, above 1 %" in found[0]
    assert "4 grain(s) ended outside the mould" in found[1] and len(found) == 2
    assert "above 1 %" in proto.shortfalls([], 8.0, float("nan"), 0)[0]
    # a loose sample (the user audit of session 48: 0.252 for a target of 0.587, unsaid)
    assert proto.shortfalls([], 8.0, 0.0, 0, 0.54, 7.9) == []
    [loose] = proto.shortfalls([], 8.0, 0.0, 0, 0.252, 5.94)
    assert loose.startswith("the sample's packing fraction is 0.252, well below "
                            "packing_fraction 0.587; its highest grain reaches 5.94 mm under "
                            "the plate at 8.00 mm"), loose


def test_a_run_records_whether_each_settling_phase_settled(micro_run):
    _, out = micro_run
    sample = json.loads((out / "sample_3" / "summary.json").read_text())
    settling = [rec for rec in sample["phases"] if rec["phase"] in ("pour", "hold", "confine")]
    assert len(settling) == 5 and all(isinstance(rec["settled"], bool) for rec in settling)
    assert "settled" not in [k for rec in sample["phases"] if rec["phase"] == "vibrate" for k in rec]
    prep = sample["stages"]["0:prepare"]
    assert isinstance(prep["warnings"], list)
    unsettled = [rec for rec in settling if not rec["settled"]]
    assert sum("reached its time limit" in w for w in prep["warnings"]) == len(unsettled)


# --- session 43's mutation audit of the files and checks that guard the results -------------
def _tiny():
    from tcd.config import parse_scenario
    text = (ROOT / "scenarios" / "tiny.toml").read_text()
    return text, parse_scenario(text, str(ROOT / "scenarios" / "tiny.toml"))


# runner.py check_run_checkpoint: a checkpoint of another seed (copied across sample_<seed>
# directories, or a batch of other seeds) is refused, naming the file
def test_a_checkpoint_of_another_seed_is_refused():
    from tcd import runner
    text, scn = _tiny()
    meta = {k: 0 for k in runner.SAMPLE_CHECKPOINT_KEYS}
    meta.update(seed=1, scenario_text=text)
    runner.check_run_checkpoint(scn, "sample_1/checkpoint.h5", meta,
                                runner.SAMPLE_CHECKPOINT_KEYS, seeds=[1])   # its own: accepted
    with pytest.raises(ValueError, match=r"sample_2/checkpoint.h5: the checkpoint holds seeds \[1\], "
                                         r"the scenario \[2\]"):
        runner.check_run_checkpoint(scn, "sample_2/checkpoint.h5", meta,
                                    runner.SAMPLE_CHECKPOINT_KEYS, seeds=[2])
    batch = {k: 0 for k in runner.BATCH_CHECKPOINT_KEYS}
    batch.update(seeds=[1, 2], scenario_text=text)
    with pytest.raises(ValueError, match=r"holds seeds \[1, 2\], the scenario \[1, 3\]"):
        runner.check_run_checkpoint(scn, "batch_checkpoint.h5", batch,
                                    runner.BATCH_CHECKPOINT_KEYS, seeds=[1, 3])


# runner.py _scenario_record / scenario_changes: a resume must share every section but the
# seeds, the description and the backend; output settings included (snapshot spacing), but
# the checkpoints' wall-clock spacing (since session 47: it changes no number)
def test_scenario_changes_cover_every_section_but_seeds_description_and_backend():
    from tcd import runner
    from tcd.config import parse_scenario
    text, scn = _tiny()
    assert text.count("checkpoint_every_s = 5") == 1
    same = text.replace("seeds = [1]", "seeds = [1, 7]").replace(
        'description = "scaled', 'description = "other').replace('[solver]', '[backend]\nprecision = "f32"\n\n[solver]').replace(
        "checkpoint_every_s = 5", "checkpoint_every_s = 600")
    assert runner.scenario_changes(text, parse_scenario(same, scn.source), "w") == []
    for old, new, line in (
            ("snapshot_every = 0.05", "snapshot_every = 0.02", "output.snapshot_every: 0.05 -> 0.02"),
            ("checkpoint_every_s = 5", "checkpoint_every_s = 5\nseries_every = 3",
             "output.series_every: 1 -> 3"),
            ("friction = 0.7", "friction = 0.5", "material.friction: 0.7 -> 0.5"),
            ("time_step = 5e-4", "time_step = 4e-4", "solver.time_step: 0.0005 -> 0.0004"),
            ('mode = "paper"', 'mode = "burgers"', "bond.mode: 'paper' -> 'burgers'"),
            ("displacement_mm = 0.4", "displacement_mm = 0.5", "stage[2].displacement_mm: 0.4 -> 0.5")):
        assert text.count(old) == 1, old
        changed = runner.scenario_changes(text, parse_scenario(text.replace(old, new), scn.source), "w")
        assert changed == [line], (old, changed)


# runner.py _shear_numbers / SERIES_UNITS / _write_series: the shear series file is in SI units
# (attributes tau_peak in Pa, d_peak and smoothing_window in m; units on every dataset and in
# the CSV header)
def test_shear_series_file_holds_si_units_and_peak_attributes(tmp_path):
    from types import SimpleNamespace
    from tcd import runner
    proto = SimpleNamespace(cfg=SimpleNamespace(smoothing_window_mm=0.1),
                            finish=lambda sim, phase, arrays, x_start: {"tau_peak_MPa": 0.9,
                                                                        "d_peak_mm": 2.4})
    numbers, attrs = runner._shear_numbers(proto, None, None, {}, tmp_path / "states.h5", None)
    assert numbers == {"tau_peak_MPa": 0.9, "d_peak_mm": 2.4}
    assert {k: attrs[k] for k in ("tau_peak", "d_peak", "smoothing_window")} == pytest.approx(
        {"tau_peak": 0.9e6, "d_peak": 2.4e-3, "smoothing_window": 1e-4})
    assert {k: v for k, v in attrs.items() if k.endswith("_units")} == {
        "tau_peak_units": "Pa", "d_peak_units": "m", "smoothing_window_units": "m"}
    arrays = {k: np.arange(3.0) for k in ("time", "displacement", "shear_force", "shear_stress",
                                          "kinetic_energy", "top_plate_force", "top_plate_z", "sweeps")}
    runner._write_series(tmp_path, "shear", arrays, attrs)
    with h5py.File(tmp_path / "shear_series.h5", "r") as f:
        units = {k: f[k].attrs["units"] for k in arrays}
        assert f.attrs["d_peak"] == pytest.approx(2.4e-3)
    assert units == {"time": "s", "displacement": "m", "shear_force": "N", "shear_stress": "Pa",
                     "kinetic_energy": "J", "top_plate_force": "N", "top_plate_z": "m", "sweeps": "1"}
    header = (tmp_path / "shear_series.csv").read_text().splitlines()[0]
    assert header == ("time [s],displacement [m],shear_force [N],shear_stress [Pa],"
                      "kinetic_energy [J],top_plate_force [N],top_plate_z [m],sweeps [1]")


# runner.py summarize: the run summary names the backend it ran on
def test_summary_records_the_arch_and_precision_and_the_means():
    from tcd import runner
    _, scn = _tiny()
    scn = scn.with_overrides(precision="f32")
    samples = [{"seed": 1, "tau_peak_MPa": 0.8, "d_peak_mm": 2.0, "wall_time_s": {"0:shear": 1.0}},
               {"seed": 2, "tau_peak_MPa": 1.0, "d_peak_mm": 3.0, "wall_time_s": {}}]
    summary = runner.summarize(scn, samples)
    assert (summary["scenario"], summary["arch"], summary["precision"]) == ("tiny", "cpu", "f32")
    assert summary["mean"]["tau_peak_MPa"] == 0.9 and summary["mean"]["d_peak_mm"] == 2.5
    assert summary["wall_time_s"] == {"sample_1": {"0:shear": 1.0}, "sample_2": {}}


# runner.py summarize: only the paper's Leutner test is compared with Table 2's experiments
def test_summary_compares_only_the_paper_s_test_with_the_experiments():
    from tcd import runner
    from tcd.config import load_scenario
    study = load_scenario(ROOT / "scenarios" / "leutner_shear.toml")
    samples = [{"seed": s, "tau_peak_MPa": 0.9, "d_peak_mm": 2.37, "stages": {"0:shear": {
        "mould_diameter_mm": 150.0, "sample_height_mm": h}}} for s, h in ((1, 118.2), (2, 118.9))]
    summary = runner.summarize(study, samples)
    assert summary["paper_test"] is True and summary["paper_test_differences"] == []
    assert summary["experiment"] == {"tau_peak_MPa": 0.898, "d_peak_mm": 2.37}
    assert summary["relative_error"]["tau_peak"] == pytest.approx(0.9 / 0.898 - 1)
    # the same scenario's samples in a narrower mould: another test
    narrow = [{**s, "stages": {"0:shear": {"mould_diameter_mm": 100.0, "sample_height_mm": 118.5}}}
              for s in samples]
    summary = runner.summarize(study, narrow)
    assert summary["paper_test"] is False and summary["relative_error"] is None
    assert summary["paper_test_differences"] == ["a mould of 100 mm (the paper's: 150 mm)"]
    assert summary["mean"]["tau_peak_MPa"] == pytest.approx(0.9)      # still averaged


# runner.py _write_sample_summary: the headline numbers are the stages' own
def test_sample_summary_lifts_each_stage_s_headline_numbers(tmp_path):
    from tcd import runner
    shear = {"tau_peak_MPa": 0.9, "d_peak_mm": 2.4, "residual_MPa": 0.5, "bonds_total": 10,
             "bonds_broken": 3, "bonds_broken_tension": 1, "bonds_broken_shear": 2, "particles": 170,
             "peak_index": 7}
    result = {"stages": {"0:prepare": {"particles": 180, "packing_fraction": 0.6,
                                       "packing_fraction_per_layer": [0.58, 0.62]},
                         "1:shear": shear}, "wall_time_s": {}}
    flat = runner._write_sample_summary(tmp_path, 5, result)
    assert json.loads((tmp_path / "summary.json").read_text()) == flat
    assert flat["seed"] == 5 and flat["packing_fraction"] == 0.6
    assert {k: flat[k] for k in shear if k != "peak_index"} == {k: v for k, v in shear.items()
                                                                if k != "peak_index"}
    assert "peak_index" not in flat



@contextlib.contextmanager
def lock_held_elsewhere(lock, holder: str):
    """Another process holding the run lock file `lock` (as a running tcd run does), saying
    `holder`; SIGKILLed at the end (its lock goes with it, the file stays)."""
    proc = subprocess.Popen(
        [sys.executable, "-c",
         "import fcntl, time\n"
         f"f = open({str(lock)!r}, 'a+')\n"
         "fcntl.flock(f, fcntl.LOCK_EX)\n"
         f"f.write({holder!r}); f.flush()\n"
         "print('locked', flush=True)\n"
         "time.sleep(120)\n"], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        yield
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()


def test_a_second_process_cannot_write_into_a_running_runs_directory(micro_run, tmp_path, capsys):
    """`tcd run --resume` (or a new run) into a directory another process still writes into
    would append to the same states.h5 and overwrite its checkpoint (session 44): it is now
    refused while that process holds the run's lock, and runs once that process is gone, even
    after a SIGKILL left the lock file behind."""
    import fcntl
    import shutil
    from tcd.runner import LOCK_FILE
    scenario, out = micro_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    (run / LOCK_FILE).unlink(missing_ok=True)
    with lock_held_elsewhere(run / LOCK_FILE, "pid 4242 on the other terminal"):
        before = {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
        capsys.readouterr()
        assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 2
        err = capsys.readouterr().err
        assert (f"{run}: another tcd run is writing into this directory (pid 4242 on the other "
                "terminal)") in err, err
        after = {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
        assert after == before              # nothing written, the lock file left as it was
        fresh = tmp_path / "fresh"          # an empty directory another run has just locked
        fresh.mkdir()
        shutil.copy(run / LOCK_FILE, fresh / LOCK_FILE)
        with open(fresh / LOCK_FILE) as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            assert run_tcd(["run", str(scenario), "--out", str(fresh)]) == 2
            assert "another tcd run is writing into this directory" in capsys.readouterr().err
        assert sorted(p.name for p in fresh.iterdir()) == [LOCK_FILE]
    # the holder was killed: its lock went with it, and the resume runs (every sample is done,
    # so it writes the summary again) and leaves its own pid in the lock file
    assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 0
    assert (run / LOCK_FILE).read_text().startswith(f"pid {os.getpid()} on ")
    assert json.loads((run / "summary.json").read_text())["samples"] == \
        json.loads((out / "summary.json").read_text())["samples"]


def test_a_sample_still_written_by_an_orphaned_worker_is_not_resumed(micro_run, tmp_path, capsys):
    """A `--jobs` worker outlives its parent when only the parent is killed, and goes on
    writing its sample: a resume (serial or with --jobs) refuses that sample while the worker
    holds its lock, before anything is written (session 44)."""
    import shutil
    from tcd.runner import LOCK_FILE
    scenario, out = micro_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    for lock in run.rglob(LOCK_FILE):
        lock.unlink()
    (run / "sample_3" / "summary.json").unlink()      # the sample is to be resumed
    with lock_held_elsewhere(run / "sample_3" / LOCK_FILE, "pid 777 on a worker"):
        before = {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
        two = tmp_path / "two_seeds.toml"        # the same scenario, with a seed to start
        two.write_text(scenario.read_text().replace("seeds = [3]", "seeds = [3, 4]", 1))
        for scn, extra in ((scenario, []), (two, ["--jobs", "2"])):
            capsys.readouterr()
            assert run_tcd(["run", str(scn), "--out", str(run), "--resume", *extra]) == 2
            err = capsys.readouterr().err
            assert (f"{run / 'sample_3'}: another tcd run is writing into this directory "
                    "(pid 777 on a worker)") in err, (extra, err)
            after = {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()
                     and p.name != LOCK_FILE}
            assert after == {p: b for p, b in before.items() if p.name != LOCK_FILE}, extra
            assert not (run / "sample_4").exists(), extra
    assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 0
    resumed, first = (json.loads((d / "sample_3" / "summary.json").read_text()) for d in (run, out))
    assert resumed["tau_peak_MPa"] == first["tau_peak_MPa"] and resumed["particles"] == first["particles"]


def _running(pid: int) -> bool:
    """Whether process `pid` runs (a zombie, ended but not reaped, does not)."""
    try:
        status = pathlib.Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "\nState:\tZ" not in status


def _parallel_run_under_way(scenario, run, stderr):
    """`tcd run SCENARIO --out RUN --jobs 2` started as a child process, returned once its
    samples 3 and 4 have both written a checkpoint (the run still going)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "tcd.cli", "run", str(scenario), "--out",
                             str(run), "--jobs", "2", "--arch", backend.arch(), "--precision",
                             backend.precision()], env=env, stdout=subprocess.DEVNULL,
                            stderr=stderr, text=True, preexec_fn=default_stop_signals)
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None and not all(
            (run / f"sample_{s}" / "checkpoint.h5").exists() for s in (3, 4)):
        time.sleep(0.1)
    if proc.poll() is not None:
        proc.communicate()
        pytest.fail("the run ended before it could be interrupted")
    return proc


@pytest.mark.skipif(not pathlib.Path("/proc/self/status").exists(), reason="needs /proc")
def test_orphaned_workers_finish_their_samples_and_end(micro_run, tmp_path):
    """A `--jobs` run whose parent is killed hard: each worker finishes its sample, then ends.
    Both workers used to sleep for ever after their samples were done, waiting for work from
    a parent that was gone (session 47's audit); a resume then finds both samples done."""
    import re
    from tcd.runner import LOCK_FILE
    scenario, out = micro_run
    two = tmp_path / "two_seeds.toml"
    two.write_text(scenario.read_text().replace("seeds = [3]", "seeds = [3, 4]", 1))
    run = tmp_path / "run"
    proc = _parallel_run_under_way(two, run, subprocess.DEVNULL)
    workers = set()
    try:
        for seed in (3, 4):
            holder = (run / f"sample_{seed}" / LOCK_FILE).read_text()
            workers.add(int(re.match(r"pid (\d+) ", holder).group(1)))
        assert proc.pid not in workers and len(workers) == 2
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.time() + 300
        while time.time() < deadline and any(_running(pid) for pid in workers):
            time.sleep(0.5)
        assert not any(_running(pid) for pid in workers), "a worker outlived its sample"
        for seed in (3, 4):
            assert (run / f"sample_{seed}" / "summary.json").exists(), seed
    finally:
        for pid in workers:
            if _running(pid):
                os.kill(pid, signal.SIGKILL)
    assert run_tcd(["run", str(two), "--out", str(run), "--resume"]) == 0
    a, b = (json.loads((d / "sample_3" / "summary.json").read_text()) for d in (out, run))
    assert a["tau_peak_MPa"] == b["tau_peak_MPa"]


@pytest.mark.skipif(not pathlib.Path(f"/proc/self/task/{os.getpid()}/children").exists(),
                    reason="needs /proc/PID/task/PID/children (CONFIG_PROC_CHILDREN)")
# (SIGINT to the whole process group, as a Ctrl-C: out of the suite from session 72, when
# once a run ran on to its end; that suite had been started in the background, so its
# children started with SIGINT ignored, and tcd rightly kept ignoring it. The child's stop
# signals are now set to their defaults (default_stop_signals); session 74)
@pytest.mark.parametrize("how", ["SIGTERM to the parent", "SIGINT to the process group"])
def test_a_parallel_run_stopped_while_its_workers_start_ends_in_one_line(micro_run, tmp_path,
                                                                         how):
    """A Ctrl-C or SIGTERM in the seconds `tcd run --jobs 2` takes to start its workers killed
    a worker, broke the pool, and ended the run in a traceback (BrokenProcessPool) or left it
    waiting for ever on the other worker, which the pool's SIGTERM could not end (session 72's
    review). The workers now start with the stop signals blocked, the run's stop reaches them
    as an event, and a stopped worker ends once idle: the run stops with the resume line."""
    from tcd.cli import EXIT_INTERRUPTED
    scenario, out = micro_run
    two = tmp_path / "two.toml"
    two.write_text(_shear_only((out / "sample_3" / "prepared.h5").as_posix(), "[3, 4]"))
    run = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "tcd.cli", "run", str(two), "--out", str(run),
                             "--jobs", "2", "--arch", backend.arch(), "--precision",
                             backend.precision()], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=default_stop_signals)
    children = pathlib.Path(f"/proc/{proc.pid}/task/{proc.pid}/children")

    def workers():      # the pool's processes (not multiprocessing's resource tracker)
        found = []
        for pid in (children.read_text().split() if children.exists() else []):
            try:
                if b"spawn_main" in pathlib.Path(f"/proc/{pid}/cmdline").read_bytes():
                    found.append(pid)
            except OSError:
                pass
        return found
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None and len(workers()) < 2:
            time.sleep(0.01)
        assert proc.poll() is None, "the run ended before its workers started"
        assert not (run / "sample_3" / "states.h5").exists(), "too late: a sample started"
        if how.startswith("SIGTERM"):
            proc.send_signal(signal.SIGTERM)
        else:
            os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == EXIT_INTERRUPTED, err[-3000:]
    assert "Traceback" not in err and "interrupted; resume with: " in err, err[-3000:]
    assert not (run / "summary.json").exists()


def test_a_stopped_parallel_run_starts_none_of_its_queued_samples(micro_run, tmp_path):
    """SIGTERM to `tcd run --jobs 2` of three samples while the first two run: both
    checkpoint and stop, the third, queued, is not started, and the parent ends at once with
    the resume command; the resume runs all three to the uninterrupted run's numbers. Session
    60 found the queued sample started in the first worker freed, the parent waiting for it
    to its end (an hour of a study's shear) without a word."""
    from tcd.cli import EXIT_INTERRUPTED
    scenario, out = micro_run
    three = tmp_path / "three_seeds.toml"
    three.write_text(scenario.read_text().replace("seeds = [3]", "seeds = [3, 4, 5]", 1))
    run = tmp_path / "run"
    proc = _parallel_run_under_way(three, run, subprocess.PIPE)
    try:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == EXIT_INTERRUPTED, err[-2000:]
    assert "interrupted; resume with: " in err and "--resume" in err
    for seed in (3, 4):             # stopped at a checkpoint, not finished
        assert (run / f"sample_{seed}" / "checkpoint.h5").exists(), seed
        assert not (run / f"sample_{seed}" / "summary.json").exists(), seed
    assert not (run / "sample_5" / "states.h5").exists(), "the queued sample was started"
    assert run_tcd(["run", str(three), "--out", str(run), "--resume"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    assert [smp["seed"] for smp in summary["samples"]] == [3, 4, 5]
    a, b = (json.loads((d / "sample_3" / "summary.json").read_text()) for d in (out, run))
    assert a["tau_peak_MPa"] == b["tau_peak_MPa"]


def test_a_parallel_worker_told_to_stop_starts_no_further_sample(tmp_path, monkeypatch):
    """The worker's side of the test above, in this process: once a `--jobs` worker has had a
    SIGTERM (between samples: its handler keeps it alive and notes it), a sample handed to it
    ends at once, before anything is written; a sample's own handler replaces the worker's
    and gives it back after."""
    from tcd import runner, signals
    monkeypatch.setattr(signals, "in_worker", False)
    monkeypatch.setattr(signals, "stop_requested", False)
    monkeypatch.setattr(signals, "stop_event", None)
    # every stop signal enter_worker takes (SIGHUP too) given back after: a SIGHUP left with
    # note_stop would be noted, not acted on, by the rest of this pytest process
    outer = {s: signal.getsignal(s) for s in signals.STOP_SIGNALS}
    for s in signals.STOP_SIGNALS:
        signal.signal(s, signals._default(s))
    try:
        signals.enter_worker()
        assert signals.in_worker and signal.getsignal(signal.SIGTERM) is signals.note_stop
        with runner.DeferredInterrupt() as interrupt:      # a sample running
            assert signal.getsignal(signal.SIGTERM) == interrupt._handler
            assert not interrupt.pending
        assert signal.getsignal(signal.SIGTERM) is signals.note_stop
        os.kill(os.getpid(), signal.SIGTERM)                # between samples: it lives on
        time.sleep(0.05)
        assert signals.stop_requested
        with pytest.raises(KeyboardInterrupt, match="sample 7 not started"):
            runner._sample_job("", "<none>", backend.arch(), backend.precision(), 7,
                               str(tmp_path / "sample_7"), False, False)
        assert not (tmp_path / "sample_7").exists()
        with runner.DeferredInterrupt() as interrupt:       # came before its handler: pending
            assert interrupt.pending
    finally:
        for s, h in outer.items():
            signal.signal(s, h)
    assert all(signal.getsignal(s) is not signals.note_stop for s in signals.STOP_SIGNALS)


def test_a_run_killed_before_its_first_checkpoint_resumes_from_the_start(micro_run, tmp_path,
                                                                         capsys):
    """A hard kill in a run's first minute (before its first checkpoint) left scenario.toml,
    run.json and a states.h5 of a few frames: `--resume` said "nothing to resume" and a new
    run "already holds results", so the folder had to be removed by hand (session 47's audit).
    Now the resume starts the sample over, to the uninterrupted run's numbers. The hidden
    temporaries that writes killed hard leave are removed by a resume (they piled up)."""
    import shutil
    scenario, out = micro_run
    run = tmp_path / "run"
    (run / "sample_3").mkdir(parents=True)
    for name in ("scenario.toml", "run.json"):
        shutil.copy(out / name, run / name)
    shutil.copy(out / "sample_3" / "states.h5", run / "sample_3" / "states.h5")
    # the temporaries of writes killed hard (atomic_path's names), and files that only look so
    stale = [run / ".run.json.k2x_9q0a.tmp", run / "sample_3" / ".states.h5.ab12cd34.tmp",
             run / "sample_3" / ".checkpoint.h5.zz99yy88.tmp"]
    kept = [run / ".notes.tmp", run / "sample_3" / "mine.tmp",
            run / "sample_3" / ".states.h5.short.tmp"]
    for path in stale + kept:
        path.write_bytes(b"\0" * 100)
    assert run_tcd(["run", str(scenario), "--out", str(run)]) == 2       # a fresh run: refused
    assert "already holds results" in capsys.readouterr().err
    assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 0
    err = capsys.readouterr().err
    assert "no checkpoint yet" in err and "removed 1 temporary file(s)" in err
    assert "removed 2 temporary file(s)" in err
    assert not any(p.exists() for p in stale) and all(p.exists() for p in kept)
    a, b = (json.loads((d / "sample_3" / "summary.json").read_text()) for d in (out, run))
    assert a["stages"] == {k: {**v, "wall_time_s": a["stages"][k]["wall_time_s"]}
                           for k, v in b["stages"].items()}
    assert io.frame_count(run / "sample_3" / "states.h5") == io.frame_count(out / "sample_3" / "states.h5")
    # a folder that holds no run at all is still refused
    (tmp_path / "other").mkdir()
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "other"), "--resume"]) == 2
    assert "nothing to resume" in capsys.readouterr().err


def test_a_preparation_says_what_it_will_pour_before_it_starts(tmp_path):
    """A size_scale of 0.1 asked for 5.9 million spheres and a minute passed without a word
    (the user audit of session 48): the counts are printed before the first course is made."""
    from tcd import runner
    from tcd.config import parse_scenario
    scn = parse_scenario(MICRO)
    assert runner.stage_sizes(scn.stages[0]) == (
        "40 binder + 40 surface spheres (80 in all, sizes x 0.3) in a 24 mm mould, layers of 4 mm")
    big = parse_scenario(MICRO.replace("particles_per_layer = 40\n", "")
                         .replace("size_scale = 0.3", "size_scale = 1.0")
                         .replace("cylinder_diameter_mm = 24.0", "cylinder_diameter_mm = 150.0")
                         .replace("layer_height_mm = 4.0", "layer_height_mm = 60.0")
                         .replace("sample_height_mm = 8.0", "sample_height_mm = 120.0")
                         .replace("column_height_mm = 100.0", "column_height_mm = 1600.0")
                         .replace("ring_height_mm = 4.0", "ring_height_mm = 60.0"))
    counts = [big.stages[0].layer_particle_count(c) for c in ("binder", "surface")]
    assert runner.stage_sizes(big.stages[0]).startswith(
        f"{counts[0]} binder + {counts[1]} surface spheres ({sum(counts)} in all")
    assert 5000 < sum(counts) < 6500          # the paper's sample: about 5200 (5857 here)


def test_a_prepared_sample_records_its_courses(micro_run):
    _, out = micro_run
    meta, _ = io.checkpoint_meta(out / "sample_3" / "prepared.h5")
    assert meta["courses"] == ["binder", "surface"]


def test_progress_is_due_ten_seconds_after_its_last_line_in_a_log(monkeypatch):
    """In a log (not a terminal) an update is due 10 s after the last line, whatever the step:
    never before the first update, not at 9.9 s, at 10 s, and not again just after it."""
    from tcd import runner
    now = [0.0]
    monkeypatch.setattr(runner.time, "perf_counter", lambda: now[0])
    bar = runner.Progress(True, "seed 1 shear:shear", 15000, 2e-4)
    assert not bar.tty
    now[0] = 50.0
    assert not bar.due()                   # no first update yet: the loop makes that one
    bar.update(0, 0.0)
    now[0] = 59.9
    assert not bar.due()
    now[0] = 60.0
    assert bar.due()
    bar.update(3, 0.0006)
    assert not bar.due()
    assert not runner.Progress(False, "off", 10, 2e-4).due()


def test_slow_steps_update_the_progress_between_hundredth_steps(micro_run, tmp_path, monkeypatch):
    """A run updates its progress every 100th step and whenever an update is due: with every
    step slow (`due` always true) each step of the shear updates it, alone and in a batch."""
    from tcd import runner
    _, out = micro_run
    steps = []
    update = runner.Progress.update
    monkeypatch.setattr(runner.Progress, "due", lambda self: True)
    monkeypatch.setattr(runner.Progress, "update",
                        lambda self, step, t, extra="": (steps.append((self.label, step)),
                                                         update(self, step, t, extra)))
    prepared = (out / "sample_3" / "prepared.h5").as_posix()
    single = tmp_path / "single.toml"
    single.write_text(_shear_only(prepared))
    assert run_tcd(["run", str(single), "--out", str(tmp_path / "one")]) == 0
    shear = [k for label, k in steps if label.startswith("seed 3 shear")]
    assert len(shear) > 5 and shear == list(range(len(shear)))
    steps.clear()
    two = tmp_path / "two.toml"
    two.write_text(_shear_only(prepared, "[3, 4]"))
    assert run_tcd(["run", str(two), "--batch", "--out", str(tmp_path / "batch")]) == 0
    batch = [k for label, k in steps if label.startswith("batch")]
    assert len(batch) > 5 and batch == list(range(len(batch)))


def test_tcd_info_of_a_stopped_shear_gives_its_travel_stress_and_peak_so_far(micro_run, tmp_path,
                                                                             monkeypatch):
    """`tcd info RUN_DIR` of a shear stopped mid-way: the ring's travel, the stress and the peak
    so far (smoothed as the summary's), from the checkpoint's series; "running" while a
    process writes into the run."""
    from tcd import runner
    _, out = micro_run
    single = tmp_path / "single.toml"
    single.write_text(_shear_only((out / "sample_3" / "prepared.h5").as_posix()))
    monkeypatch.setattr(runner, "DeferredInterrupt", _interrupt_after(25))
    with pytest.raises(KeyboardInterrupt):
        runner.run_scenario(load_here(single), tmp_path / "cut", progress=False)
    ck = tmp_path / "cut" / "sample_3" / "checkpoint.h5"
    arrays, meta = io.load_checkpoint(ck)
    d, tau = arrays["series/displacement"], arrays["series/shear_stress"]
    assert len(d) > 10 and meta["step_in_phase"] < meta["phase"]["steps"]
    from tcd.config import parse_scenario
    window = parse_scenario(single.read_text(), str(single)).stages[0].smoothing_window_mm * 1e-3
    peak, at, _ = obs.peak_of(d, tau, window)
    so_far = (f"t = {meta['time']:.4f} s; the ring at {d[-1] * 1e3:.3f} mm, {tau[-1] / 1e6:.4g} "
              f"MPa, peak so far {peak / 1e6:.4g} MPa at {at * 1e3:.3g} mm; checkpoint "
              "checkpoint.h5 written 20")
    text = runner.run_info(tmp_path / "cut")
    assert "sample_3: stopped in stage 1 of 1 (shear), phase 1 ('shear') at step " in text, text
    assert so_far in text, text
    with runner.run_lock(tmp_path / "cut"):
        text = runner.run_info(tmp_path / "cut")
    assert "sample_3: running, its last checkpoint in stage 1 of 1 (shear), " in text, text
    assert so_far in text, text


def test_a_finished_run_resumed_says_so_and_info_says_when_and_what_a_kill_left(
        micro_run, tmp_path, capsys, monkeypatch):
    """Session 69's kill-and-resume trials: `--resume` of a finished run rewrote its summary
    without a word; with SOURCE_DATE_EPOCH set (reproducible bytes) `tcd info` said a
    checkpoint was "written 1970-01-01...", the file's `created` attribute."""
    import shutil
    import h5py
    from tcd import runner
    scenario, out = micro_run
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    capsys.readouterr()
    assert run_tcd(["run", str(scenario), "--out", str(copy), "--resume"]) == 0
    assert "every sample was already done; nothing to resume" in capsys.readouterr().err
    (copy / "summary.json").unlink()
    (copy / "sample_3" / "summary.json").unlink()
    with h5py.File(copy / "sample_3" / "checkpoint.h5", "a") as f:
        f.attrs["created"] = "1970-01-01T00:00:00+00:00"
    info = runner.run_info(copy)
    assert "checkpoint checkpoint.h5 written 20" in info and "1970" not in info, info
    assert "left behind" not in info, info
    # what a hard kill leaves, which the resume clears, is named (the trials' t2, t9, t16)
    (copy / "sample_3" / ".states.h5.abcd1234.tmp").write_bytes(b"half a file")
    with h5py.File(copy / "sample_3" / "checkpoint.h5", "a") as f:
        meta = json.loads(f.attrs["meta"])
        meta["frames"] -= 2
        f.attrs["meta"] = json.dumps(meta)
    info = runner.run_info(copy)
    assert ("; left behind: 1 temporary file(s) of an interrupted write (.states.h5.abcd1234.tmp)"
            " and 2 frame(s) of states.h5 written after that checkpoint (--resume removes them)"
            ) in info, info


def _damage(path: pathlib.Path) -> None:
    """4096 bytes of 0xff over the middle of `path` (a disk's or another program's doing)."""
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 4096] = b"\xff" * 4096
    path.write_bytes(bytes(data))


def _unfinished(out: pathlib.Path, run: pathlib.Path) -> pathlib.Path:
    """A copy of the finished run `out` whose sample and run summaries are gone: a run stopped
    after its last checkpoint, which --resume finishes."""
    import shutil
    shutil.copytree(out, run)
    for path in (run / "summary.json", run / "sample_3" / "summary.json"):
        path.unlink()
    return run


@pytest.mark.parametrize("name", ["checkpoint.h5", "states.h5", "prepared.h5"])
def test_a_resume_refuses_a_sample_whose_files_are_damaged_writing_nothing(micro_run, tmp_path,
                                                                          capsys, name):
    """Session 70's probe: a checkpoint.h5 with 4096 bytes overwritten stopped --resume with a
    traceback (RuntimeError "Object visitation failed", exit 1); a damaged states.h5 or
    prepared.h5 was kept as it was, unreadable, and the run ended with status 0. Now the
    resume reads each file it goes on from whole first, and refuses with one line naming the
    file and what to do, having written nothing."""
    scenario, out = micro_run
    run = _unfinished(out, tmp_path / "run")
    _damage(run / "sample_3" / name)
    before = {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    capsys.readouterr()
    assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tcd: error: {run / 'sample_3' / name}: ") and err.count("\n") == 1, err
    assert "damaged" in err and f"move {run / 'sample_3'} away" in err, err
    assert {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()} == before
    # the same run undamaged resumes to the end
    whole = _unfinished(out, tmp_path / "whole")
    assert run_tcd(["run", str(scenario), "--out", str(whole), "--resume"]) == 0
    assert (whole / "summary.json").is_file()


def test_a_resume_refuses_a_sample_that_lost_its_checkpoint_after_a_stage_ended(micro_run,
                                                                               tmp_path, capsys):
    """Session 70's probe: with checkpoint.h5 deleted after the preparation had ended, --resume
    took the run for one stopped before its first checkpoint and ran the sample again from the
    start, overwriting prepared.h5 and the preparation's series. Now it is refused (nothing
    written) and `tcd info` says why; a sample folder moved away runs again from the start."""
    scenario, out = micro_run
    run = _unfinished(out, tmp_path / "run")
    (run / "sample_3" / "checkpoint.h5").unlink()
    before = {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    capsys.readouterr()
    assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tcd: error: {run / 'sample_3' / 'checkpoint.h5'} is missing, yet "
                          "the sample holds the results of a stage (prepare_series.csv, "
                          "prepare_series.h5, prepared.h5, shear_series.csv, "
                          "shear_series.h5)"), err
    assert {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()} == before
    from tcd import runner
    assert "sample_3: its checkpoint.h5 is missing, yet it holds the results of a stage: " \
           "--resume refuses it" in runner.run_info(run)
    (run / "sample_3").rename(tmp_path / "kept_sample_3")
    assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 0
    assert "every sample starts from the beginning" in capsys.readouterr().err
    a, b = (json.loads((d / "sample_3" / "summary.json").read_text()) for d in (out, run))
    assert a["tau_peak_MPa"] == b["tau_peak_MPa"] and a["stages"].keys() == b["stages"].keys()


def test_a_batch_resume_refuses_a_damaged_batch_checkpoint(micro_run, tmp_path, capsys):
    """A damaged batch_checkpoint.h5 is refused as a sample's checkpoint is: one line naming
    it (it was a traceback from h5py), nothing written."""
    import shutil
    scenario_file, out = micro_run
    scenario = tmp_path / "shear.toml"
    scenario.write_text(_shear_only((out / "sample_{seed}" / "prepared.h5").as_posix()))
    run = tmp_path / "batched"
    run.mkdir()
    shutil.copy(out / "sample_3" / "checkpoint.h5", run / "batch_checkpoint.h5")
    _damage(run / "batch_checkpoint.h5")
    before = {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    capsys.readouterr()
    assert run_tcd(["run", str(scenario), "--out", str(run), "--batch", "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tcd: error: {run / 'batch_checkpoint.h5'}: ") and "damaged" in err
    assert "start the batch again in a new --out directory" in err and err.count("\n") == 1, err
    assert {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()} == before


def _tcd_run_command(scenario, out) -> list:
    return [sys.executable, "-m", "tcd.cli", "run", str(scenario), "--out", str(out),
            "--arch", backend.arch(), "--precision", backend.precision()]


def _same_end(a: pathlib.Path, b: pathlib.Path) -> None:
    one = io.read_series(a / "sample_3" / "shear_series.h5")
    two = io.read_series(b / "sample_3" / "shear_series.h5")
    for key in ("displacement", "shear_stress", "bonds_intact"):
        assert np.array_equal(one[key], two[key]), key


def test_a_run_whose_reader_goes_away_runs_to_its_end(micro_run, tmp_path):
    """`tcd run ... | head -1`: the run stopped at Taichi's banner (a BrokenPipeError) with
    status 0, having run nothing (session 70's probe). Its report's reader gone, it now runs
    on, and ends with its status and its files."""
    scenario, out = micro_run
    run = tmp_path / "run"
    # as in a shell: Taichi's print buffer not turned off by the test suite (conftest)
    env = dict({k: v for k, v in os.environ.items() if k != "TI_ENABLE_PYBUF"},
               PYTHONPATH=str(ROOT))
    with open(tmp_path / "stderr.txt", "w") as log:
        proc = subprocess.Popen(_tcd_run_command(scenario, run), env=env,
                                stdout=subprocess.PIPE, stderr=log)
        assert proc.stdout.readline()           # the first line, as `head -1` reads it
        proc.stdout.close()
        assert proc.wait(timeout=300) == 0
    assert (run / "summary.json").is_file()
    _same_end(out, run)
    # its guarded sys.stdout did not make Taichi print after every kernel launch (taking
    # the run for one in a notebook)
    assert "Graphical python shell" not in (tmp_path / "stderr.txt").read_text()


@pytest.mark.parametrize("hangup", ["ignored", "default"])
def test_a_run_whose_terminal_closes_stops_at_a_checkpoint_or_runs_on(micro_run, tmp_path,
                                                                      hangup):
    """A run in a terminal (here a pseudo-terminal it controls) that is closed: SIGHUP ended it
    at once, losing the work since its last checkpoint; with SIGHUP ignored (the terminal
    gone, the process alive) a progress line or its last line failed with EIO, status 74
    (session 70's probe). Now SIGHUP stops it at the end of its step with a checkpoint
    (status 130), and its --resume ends as the uninterrupted run; with SIGHUP ignored it runs
    to its end, status 0."""
    import fcntl
    import pty
    import termios
    scenario, out = micro_run
    run = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    master, slave = pty.openpty()

    def controlled():       # the pseudo-terminal is the run's controlling terminal
        fcntl.ioctl(0, termios.TIOCSCTTY, 0)
        default_stop_signals()          # "default" whatever the shell that started the suite
        if hangup == "ignored":
            signal.signal(signal.SIGHUP, signal.SIG_IGN)
    proc = subprocess.Popen(_tcd_run_command(scenario, run), env=env, stdin=slave,
                            stdout=slave, stderr=slave, start_new_session=True,
                            preexec_fn=controlled)
    os.close(slave)
    ck = run / "sample_3" / "checkpoint.h5"
    try:
        deadline = time.time() + 240
        while time.time() < deadline and proc.poll() is None:
            with contextlib.suppress(OSError):      # keep the terminal's buffer from filling
                import select
                while select.select([master], [], [], 0)[0] and os.read(master, 65536):
                    pass
            if ck.exists():
                with contextlib.suppress(Exception):
                    if io.checkpoint_meta(ck)[0]["phase_index"] >= 1:
                        break
            time.sleep(0.1)
        assert proc.poll() is None, "the run ended before its terminal could be closed"
    finally:
        os.close(master)                    # the terminal closes
    if hangup == "ignored":
        assert proc.wait(timeout=300) == 0
        assert (run / "summary.json").is_file()
    else:
        assert proc.wait(timeout=300) == 130
        assert not (run / "summary.json").exists()
        assert run_tcd(["run", str(scenario), "--out", str(run), "--resume"]) == 0
    _same_end(out, run)


def test_a_run_refused_by_another_runs_lock_leaves_that_runs_records(micro_run, tmp_path,
                                                                     capsys, monkeypatch):
    """A new run looks at its --out directory, finds it missing, and is then refused because
    another run created it meanwhile and holds its lock: its clean-up took everything it had
    not seen for its own records and removed the other run's scenario.toml, run.json and lock
    file (session 70's probe; a race of two runs started at once). Now only a run that held
    the lock takes anything back."""
    import shutil
    from tcd import runner
    from tcd.runner import LOCK_FILE
    scenario, out = micro_run
    race = tmp_path / "race"
    race.mkdir()
    for name in ("scenario.toml", "run.json"):
        shutil.copy(out / name, race / name)
    real = runner._paths_in
    looks = []

    def looked_before_the_other_run_began(path):
        looks.append(path)
        return None if len(looks) == 1 else real(path)
    monkeypatch.setattr(runner, "_paths_in", looked_before_the_other_run_began)
    with lock_held_elsewhere(race / LOCK_FILE, "pid 4343 on the other terminal"):
        assert run_tcd(["run", str(scenario), "--out", str(race)]) == 2
        assert "another tcd run is writing into this directory" in capsys.readouterr().err
        assert sorted(p.name for p in race.iterdir()) == [LOCK_FILE, "run.json", "scenario.toml"]
    assert looks == [race]


def test_a_run_whose_sample_folder_is_deleted_under_it_does_not_promise_its_files(
        micro_run, tmp_path, capsys, monkeypatch):
    """A user deleted a new run's sample folder while it ran: the run stopped at its next
    write (exit 74), took its records back (nothing of it was left) and removed its --out
    directory, yet said "the files written before are intact ... --resume" (session 71's
    probe). Now it says that nothing is left to resume."""
    import shutil
    from tcd import io
    _, out = micro_run
    scenario = tmp_path / "shear.toml"
    scenario.write_text(_shear_only((out / "sample_{seed}" / "prepared.h5").as_posix()))
    real = io.append_frame

    def deleted_by_the_user(path, *args, **kwargs):
        shutil.rmtree(pathlib.Path(path).parent)
        return real(path, *args, **kwargs)
    monkeypatch.setattr(io, "append_frame", deleted_by_the_user)
    run = tmp_path / "run"
    capsys.readouterr()
    assert run_tcd(["run", str(scenario), "--out", str(run)]) == 74
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("tcd: error: ") and "No such file or directory" in err, err
    assert "nothing of this run is left to resume" in err and "intact" not in err, err
    assert not run.exists()


def test_a_shear_from_a_damaged_prepared_sample_is_refused_in_one_line(micro_run, tmp_path,
                                                                       capsys):
    """A shear scenario whose `sample` file is damaged stopped `tcd run` (with --batch too)
    and `tcd info SCENARIO` with a traceback (h5py's RuntimeError; session 71's probe)."""
    import shutil
    _, out = micro_run
    shutil.copy(out / "sample_3" / "prepared.h5", tmp_path / "s_3.h5")
    _damage(tmp_path / "s_3.h5")
    scenario = tmp_path / "shear.toml"
    scenario.write_text(_shear_only((tmp_path / "s_{seed}.h5").as_posix()))
    from tcd.cli import main
    capsys.readouterr()
    for argv in (["run", str(scenario), "--out", str(tmp_path / "run")],
                 ["run", str(scenario), "--out", str(tmp_path / "batch"), "--batch"],
                 ["info", str(scenario)]):
        assert (run_tcd(argv) if argv[0] == "run" else main(argv)) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(f"tcd: error: {tmp_path / 's_3.h5'}: ") and "damaged" in err, err
        assert err.count("\n") == 1, err
    assert not (tmp_path / "run").exists() and not (tmp_path / "batch").exists()


def test_the_commands_tcd_info_suggests_are_quoted_for_the_shell(micro_run, tmp_path):
    """`tcd info RUN` printed `tcd figures t/run α b`, which a shell splits at the spaces
    (session 72's review); the resume command's --out likewise."""
    import shlex
    import shutil
    from tcd import runner
    _, out = micro_run
    run = tmp_path / "run α b"
    shutil.copytree(out, run)
    info = runner.run_info(run)
    assert f"`tcd figures {shlex.quote(str(run))}`" in info, info
    (run / "summary.json").unlink()
    info = runner.run_info(run)
    assert f" --out {shlex.quote(str(run))} --resume`" in info, info
    command = info.split("resume it with `", 1)[1].split("`", 1)[0]
    assert shlex.split(command)[shlex.split(command).index("--out") + 1] == str(run)


def test_tcd_info_tells_a_started_sample_from_a_refused_one_and_resumes_as_begun(micro_run,
                                                                                tmp_path):
    """`tcd info RUN` said of every started sample without a checkpoint that --resume refused
    it (a generator is always true), and its resume command left out the --precision and
    --seeds the run began with, so that command was refused or ran the seeds left out
    (session 72's review)."""
    import shutil
    from tcd import runner
    _, out = micro_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    (run / "summary.json").unlink()
    sample = run / "sample_3"
    for p in sample.iterdir():
        if p.name not in ("states.h5", ".tcd.lock"):
            p.unlink()
    started = json.loads((run / "run.json").read_text())
    other = "f32" if started["precision"] == "f64" else "f64"
    (run / "run.json").write_text(json.dumps({**started, "precision": other, "seeds": [3]}))
    text = (run / "scenario.toml").read_text()
    (run / "scenario.toml").write_text(text.replace("seeds = [3]", "seeds = [3, 4]", 1))
    info = runner.run_info(run)
    assert "sample_3: started, no checkpoint yet" in info, info
    assert f" --precision {other} --seeds 3 --resume`" in info, info
    (sample / "prepared.h5").write_bytes(b"")
    assert "sample_3: its checkpoint.h5 is missing" in runner.run_info(run)
