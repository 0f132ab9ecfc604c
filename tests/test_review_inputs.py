"""Session 69's review of the commands and of the Python API as a user who feeds them bad
input: each test is a defect that review found (what tcd did before is in its docstring),
checked on the command itself or on the function it calls. No simulation runs longer than a
few steps of a few grains."""
import errno
import json
import pathlib
import shutil

import h5py
import numpy as np
import pytest

from tcd import bench, compare, config, figures, packing, runner, walls
from tcd.simulation import BondLaw, Simulation, SolverSettings
from tcd.cli import main
from test_cli import SAMPLE, SCENARIO, _one_frame_states, _states_with, _with  # noqa: F401
from test_figures import _write_sample

pytestmark = [pytest.mark.filterwarnings("ignore::DeprecationWarning"),
              pytest.mark.filterwarnings("ignore:.*summary.json missing:UserWarning")]

SHEAR = 'name = "s"\nseeds = {seeds}\n[[stage]]\nkind = "shear"\nsample = "{sample}"\n'


def _cli_scenario(tmp_path):
    """tests/test_cli.py's scenario (a prepare and a shear stage) in a file."""
    path = tmp_path / "cli.toml"
    path.write_text(SCENARIO)
    return path


def _shear_scenario(tmp_path, sample, seeds=(1,)):
    path = tmp_path / "s.toml"
    path.write_text(SHEAR.format(seeds=list(seeds), sample=sample))
    return path


# --- tcd info SCENARIO reads the sample files as tcd run does ----------------------------------
def test_info_of_a_scenario_reads_its_sample_files_as_run_does(tmp_path, capsys):
    """`tcd info` said "(1 file, all present)" of a sample that was not an HDF5 file, and of a
    sample of another density than the scenario's, which `tcd run` refused at once."""
    junk = tmp_path / "junk.h5"
    junk.write_text("hello")
    assert main(["info", str(_shear_scenario(tmp_path, junk))]) == 2
    assert f"{junk}: not an HDF5 file" in capsys.readouterr().err
    good = _shear_scenario(tmp_path, SAMPLE)
    assert main(["info", str(good), "--set", "material.density=3000"]) == 2
    err = capsys.readouterr().err
    assert f"{SAMPLE} (seed 1)" in err and "density is 3000" in err, err
    assert main(["info", str(good)]) == 0
    assert "all present and read as prepared samples" in capsys.readouterr().out


def test_a_run_of_some_seeds_needs_only_their_sample_files(tmp_path, capsys, runner_calls):
    """`tcd run S --seeds 1` refused a study whose seed 2 had no sample file yet: --seeds is
    how a study is split across machines, each with its own samples."""
    shutil.copy(SAMPLE, tmp_path / "samp_1.h5")
    scenario = _shear_scenario(tmp_path, "samp_{seed}.h5", seeds=(1, 2))
    assert main(["run", str(scenario), "--seeds", "1", "--out", str(tmp_path / "o")]) == 0
    assert list(runner_calls[0]["scenario"].seeds) == [1]
    assert main(["run", str(scenario), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "stage[1].sample: no such sample file" in err and "samp_2.h5" in err, err
    # what a --jobs worker and a --resume read back: the stored text, checked for their seeds
    text = scenario.read_text()
    assert list(config.parse_scenario(text, str(scenario), seeds=[1]).seeds) == [1, 2]
    with pytest.raises(config.ScenarioNotFoundError, match="samp_2.h5"):
        config.parse_scenario(text, str(scenario))


def test_a_sample_path_that_is_a_directory_is_named_as_one(tmp_path):
    with pytest.raises(config.ScenarioError, match=f"{tmp_path} is a directory, not a sample"):
        config.load_scenario(_shear_scenario(tmp_path, tmp_path))


# --- tcd info FILE.h5 checks the arrays of every frame -----------------------------------------
@pytest.mark.parametrize("key, edit, words", [
    ("contacts/i", _with(0, 10**6), "key 'contacts/i' has indices in"),
    ("particles/radius", _with(0, -1e-3), "key 'particles/radius' holds 1 radii"),
    ("walls/kind", _with(0, 77), "key 'walls/kind' has values outside {0 plane, 1 cylinder}"),
])
def test_info_of_a_states_file_checks_its_frames_arrays(tmp_path, capsys, key, edit, words):
    """`tcd info` printed its summary, status 0, of frames that `tcd export` and `tcd render`
    refused (docs/usage.md: info, export and analyse check the arrays they read)."""
    path = _states_with(tmp_path, key, edit)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tcd: error: {path}: frame 0: ") and words in err, err


def test_info_names_the_frames_whose_positions_are_not_finite(tmp_path, capsys):
    path = _states_with(tmp_path, "particles/x", _with(0, np.nan))
    assert main(["info", str(path)]) == 0
    assert "warning: 1 frame(s) hold positions that are not finite" in capsys.readouterr().out


def test_a_frame_without_radii_is_refused_by_info_and_export(tmp_path, capsys):
    """`tcd export` wrote such a frame with every radius 0; `tcd analyse` said KeyError."""
    path = _one_frame_states(tmp_path)
    with h5py.File(path, "a") as f:
        del f["frames/000000/particles/radius"]
    for argv in (["info", str(path)], ["export", str(path), "--out", str(tmp_path / "vtk")]):
        assert main(argv) == 2, argv
        assert "key 'particles/radius' is required" in capsys.readouterr().err
    assert not (tmp_path / "vtk").exists() or not any((tmp_path / "vtk").iterdir())


# --- a batch checkpoint is not drawn or analysed as one sample ---------------------------------
def test_render_and_analyse_refuse_a_batch_checkpoint(tmp_path, capsys):
    """`tcd render` drew the samples of a `--batch` checkpoint inside each other in one mould,
    `tcd analyse` averaged them in one row."""
    from tcd import render
    path = tmp_path / "batch_checkpoint.h5"
    shutil.copy(SAMPLE, path)
    with h5py.File(path, "a") as f:
        n = f["arrays/particles/x"].shape[0]
        f["arrays/particles/system"] = (np.arange(n) >= n // 2).astype(np.int32)
    with pytest.raises(ValueError, match="a batch checkpoint, 2 samples side by side"):
        render.load_frame(path)
    assert main(["analyse", str(path), "--out", str(tmp_path / "a")]) == 2
    assert "tcd analyse reads one sample" in capsys.readouterr().err
    assert not list(tmp_path.glob("a.*"))


# --- tcd figures and tcd compare: nothing replaced when an output cannot be ------------------
def test_figures_replace_nothing_when_one_output_cannot_be_written(tmp_path, capsys):
    """With table2.md a directory, `tcd figures` replaced fig4 with the new run's, then failed
    with status 74: the folder mixed two runs' figures."""
    run = tmp_path / "run"
    _write_sample(run, 1, 0.85e6, 2.2e-3)
    out = tmp_path / "figs"
    out.mkdir()
    (out / "fig4_stress_displacement.png").write_bytes(b"the earlier run's figure")
    (out / "table2.md").mkdir()
    assert main(["figures", str(run), "--out", str(out)]) == 2
    assert "table2.md: exists and is not a file" in capsys.readouterr().err
    assert (out / "fig4_stress_displacement.png").read_bytes() == b"the earlier run's figure"
    assert sorted(p.name for p in out.iterdir()) == ["fig4_stress_displacement.png", "table2.md"]


def test_a_series_without_a_finite_stress_is_named(tmp_path):
    """The warning said "peak_of: no finite stress values", naming neither file nor series."""
    run = tmp_path / "run"
    _write_sample(run, 1, 0.85e6, 2.2e-3)
    _write_sample(run, 2, 0.85e6, 2.2e-3)
    series = run / "sample_2" / "shear_series.h5"
    with h5py.File(series, "a") as f:
        f["shear_stress"][...] = np.nan
    with pytest.warns(figures.FigureWarning,
                      match=f"sample 2 skipped: {series}: series 'shear_stress' holds no finite"):
        figures.make_figures(run, tmp_path / "out", render=False)


@pytest.mark.parametrize("labels, words", [
    (["a", ""], "label '': a label must be a non-empty name"),
    (["a|b", "c"], "label 'a|b'"),
    (["A", "A"], "labels ['A', 'A'] repeat a name$"),
])
def test_compare_refuses_labels_that_cannot_head_a_column(tmp_path, labels, words):
    """An empty label was accepted, a '|' split compare.md's table, and a repeated --labels
    was told to "give --labels"."""
    runs = [tmp_path / "r1", tmp_path / "r2"]
    for run in runs:
        run.mkdir()
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")
                       .replace("|", r"\|")):
        compare.compare_runs(runs, tmp_path / "out", labels)


def test_compare_replaces_nothing_when_one_output_cannot_be_written(tmp_path, capsys):
    runs = []
    for name in ("r1", "r2"):
        runs.append(tmp_path / name)
        _write_sample(runs[-1], 1, 0.85e6, 2.2e-3)
    out = tmp_path / "cmp"
    (out / "compare.md").mkdir(parents=True)
    assert main(["compare", *map(str, runs), "--out", str(out)]) == 2
    assert "compare.md: exists and is not a file" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["compare.md"]


# --- tcd bench ---------------------------------------------------------------------------------
def test_scaling_outputs_keep_a_dotted_prefix_and_are_checked_before_the_first_size(tmp_path):
    """`--out sc/res.v2` wrote sc/res.csv; with the CSV's name a directory, the first size ran
    (minutes to hours) before the write failed."""
    assert bench.scaling_paths("sc/res.v2") == (pathlib.Path("sc/res.v2.csv"),
                                                pathlib.Path("sc/res.v2.png"))
    assert bench.scaling_paths("sc/res.png") == (pathlib.Path("sc/res.csv"),
                                                 pathlib.Path("sc/res.png"))
    (tmp_path / "out.csv").mkdir()
    with pytest.raises(ValueError, match="out.csv exists and is not a file"):
        bench.scaling(sizes=[300], steps=3, out=str(tmp_path / "out"))
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]


def test_bench_shear_takes_particles_or_a_sample_not_both(tmp_path, capsys):
    """`--particles` was ignored beside `--sample`; a directory given as --sample was "no such
    file"."""
    assert main(["bench", "shear", "--sample", str(SAMPLE), "--particles", "300"]) == 2
    assert "--particles and --sample" in capsys.readouterr().err.splitlines()[-1]
    assert main(["bench", "shear", "--sample", str(tmp_path)]) == 2
    assert f"{tmp_path} is a directory" in capsys.readouterr().err


# --- tcd run, tcd info, tcd render: paths and settings -----------------------------------------
def test_resume_into_a_file_says_it_is_a_file(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["run", str(_cli_scenario(tmp_path)), "--out", str(afile), "--resume"]) == 2
    assert f"{afile} is a file, not a run directory" in capsys.readouterr().err


def test_a_run_whose_output_folder_cannot_be_made_is_an_io_error(tmp_path, capsys, stub):
    """`--out /proc/x`: the system's "no such file" was taken for a usage error (status 2,
    "[Errno 2] ..."), not the file system's refusal of an output (status 74, the path named)."""
    def run_scenario(*args, **kwargs):
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", "/proc/x")
    stub("runner", run_scenario=run_scenario)
    assert main(["run", str(_cli_scenario(tmp_path)), "--out", str(tmp_path / "o")]) == 74
    err = capsys.readouterr().err
    assert err.startswith("tcd: error: /proc/x: No such file or directory; the files written"), err
    # a scenario that does not exist stays a usage error
    assert main(["run", str(tmp_path / "missing.toml")]) == 2


def test_info_of_a_data_file_with_set_says_set_is_for_scenarios(tmp_path, capsys):
    """It said the file was "not UTF-8 text (byte 0)"."""
    path = _one_frame_states(tmp_path)
    assert main(["info", str(path), "--set", "a=1"]) == 2
    assert "--set applies to a scenario file" in capsys.readouterr().err


def test_analyse_names_a_directory_in_place_of_its_output(tmp_path, capsys):
    """It said the directory "exists and is not an output of tcd analyse (a run's series?)"."""
    (tmp_path / "an.h5").mkdir()
    assert main(["analyse", str(SAMPLE), "--out", str(tmp_path / "an")]) == 2
    assert f"{tmp_path / 'an.h5'} is a directory" in capsys.readouterr().err


def test_a_shear_stage_s_two_geometry_problems_are_both_named(tmp_path, capsys):
    """The displacement against the mould and the rings against the sample's height were an
    `elif`: the second showed only once the first was mended."""
    path = tmp_path / "s.toml"
    path.write_text(SCENARIO)
    assert main(["info", str(path), "--set", "stage[2].displacement_mm=200",
                 "--set", "stage[2].ring_height_mm=50"]) == 2
    err = capsys.readouterr().err
    assert "stage[2].displacement_mm: 200 mm is not smaller" in err, err
    assert "stage[2].ring_height_mm: two rings of 50 mm" in err, err


def test_a_key_set_twice_is_refused(tmp_path, capsys):
    """The last of two `--set` of one key was taken silently."""
    assert main(["info", str(_cli_scenario(tmp_path)), "--set", "solver.tolerance=1e-5",
                 "--set", "solver.tolerance=1e-6"]) == 2
    assert "solver.tolerance: set twice by --set (1e-05, then 1e-06)" in capsys.readouterr().err


def test_render_makes_no_folder(tmp_path, capsys):
    """`tcd render ... --out /nonexist/a.png` created /nonexist; export and analyse refuse."""
    out = tmp_path / "no" / "such" / "a.png"
    assert main(["render", str(SAMPLE), "--out", str(out)]) == 2
    assert f"directory {out.parent} does not exist" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


def test_a_prepared_sample_in_place_of_a_checkpoint_is_named_so(tmp_path):
    """`tcd info RUN` said "(...checkpoint.h5: 'stage')", a bare KeyError."""
    run = tmp_path / "run"
    (run / "sample_1").mkdir(parents=True)
    (run / "scenario.toml").write_text(SCENARIO)
    shutil.copy(SAMPLE, run / "sample_1" / "checkpoint.h5")
    text = runner.run_info(run)
    assert "its meta lacks 'stage': not a run's checkpoint" in text, text


def test_a_pouring_column_too_wide_to_hold_its_lattice_is_named():
    """A cylinder of 1e300 mm: NumPy's "Maximum allowed size exceeded"."""
    with pytest.raises(ValueError, match="lattice spacings .* in radius: at most 3000"):
        packing.lattice_column(np.full(10, 1e-3), 1e297, 0.0, np.random.default_rng(1))


def test_the_figure_file_lists_name_what_the_commands_write(tmp_path):
    """refuse_outputs checks FIGURE_FILES and COMPARE_FILES: they must hold every file name
    the two commands write (a new figure left out would be replaced unchecked)."""
    run = tmp_path / "run"
    _write_sample(run, 1, 0.85e6, 2.2e-3)
    (run / "summary.json").write_text(json.dumps({"samples": [
        {"seed": 1, "tau_peak_MPa": 0.85, "d_peak_mm": 2.2}]}))
    with pytest.warns(figures.FigureWarning):
        written = figures.make_figures(run, tmp_path / "f")
    assert {p.name for p in written} <= set(figures.FIGURE_FILES)
    runs = [run, tmp_path / "run2"]
    _write_sample(runs[1], 1, 0.80e6, 2.1e-3)
    written = compare.compare_runs(runs, tmp_path / "c")
    assert {p.name for p in written} == set(compare.COMPARE_FILES)


# --- the Python API ----------------------------------------------------------------------------
def _pair(**kw):
    return Simulation(np.full(2, 1e-3), [[0, 0, 0.002], [0, 0, 0.006]],
                      walls=[walls.plane((0, 0, 0), (0, 0, 1))], **kw)


def test_settings_hold_python_numbers():
    """An np.float32 time step made the clock float32 (it stops advancing near 2048 s with
    H = 1e-4); gravity was kept as given: strings failed in a kernel ("type object 'float' has
    no attribute 'to_string'"), an array made two settings unequal to compare."""
    s = SolverSettings(time_step=np.float32(1e-4), max_sweeps=np.int64(10),
                       gravity=np.array([0, 0, -9.81]))
    assert type(s.time_step) is float and type(s.max_sweeps) is int
    assert s.gravity == (0.0, 0.0, -9.81) and all(type(g) is float for g in s.gravity)
    assert hash(s) == hash(SolverSettings(time_step=float(np.float32(1e-4)), max_sweeps=10))
    assert SolverSettings(gravity=[0, 0, -9.81]) == SolverSettings()
    with pytest.raises(ValueError, match="gravity must be a finite 3-vector of numbers"):
        SolverSettings(gravity=["0", "0", "-9.81"])
    assert type(BondLaw(yield_stress=np.float32(2e6)).yield_stress) is float
    sim = _pair(settings=SolverSettings(time_step=np.float32(1e-4)))
    try:
        sim.step(3)
        assert type(sim.time) is float
    finally:
        sim.close()


def test_batch_names_the_setting_that_differs_and_refuses_what_is_not_a_simulation():
    a, b = _pair(), _pair(settings=SolverSettings(tolerance=1e-5))
    try:
        with pytest.raises(ValueError, match=r"in settings: tolerance 1e-05 != 0.0001$"):
            Simulation.batch([a, b])
    finally:
        a.close()
        b.close()
    with pytest.raises(TypeError, match="item 0 is a int"):
        Simulation.batch([1, 2])


def test_set_positions_and_states_refuse_two_grains_at_one_centre():
    """The constructor refused them (no contact normal); set_positions and load_state_dict
    installed them, and the pair stayed merged for ever."""
    sim = _pair()
    try:
        x = sim.positions()
        x[1] = x[0]
        with pytest.raises(ValueError, match="particles 0 and 1 have the same centre"):
            sim.set_positions(x)
        d = sim.state_dict()
        d["particles/x"] = x
        with pytest.raises(ValueError, match="particles 0 and 1 have the same centre"):
            sim.load_state_dict(d)
        assert sim.positions()[1, 2] == pytest.approx(0.006)       # unchanged
    finally:
        sim.close()


def test_masses_that_are_zero_or_infinite_in_the_backend_are_refused(precision):
    """A density of 1e-300 or a radius of 1e-120 m gave infinite inverse masses, NaN at the
    first step, with only NumPy's "divide by zero" warning."""
    with pytest.raises(ValueError, match="density 1e-300 kg/m\\^3 and radius 0.001 m"):
        _pair(density=1e-300)
    with pytest.raises(ValueError, match="radius 1e-120 m \\(particle 0\\)"):
        Simulation([1e-120, 1e-3], [[0, 0, 0.002], [0, 0, 0.006]], cell_size=0.01)


def test_a_state_with_bad_bonds_or_layers_is_refused_and_leaves_the_simulation_as_it_was():
    """Self-bonds made NaN, duplicated bonds doubled a stiffness, bonds of area 0 never broke,
    a layer id of 2**40 was stored as -2**31; and a state refused for its sample_index had
    already been written into the simulation."""
    sim = Simulation(np.full(2, 1e-3), [[0, 0, 0.002], [0, 0, 0.0040001]])
    try:
        sim.create_bonds(1e-3)
        good = sim.state_dict()
        assert len(good["bonds/i"]) == 1
        cases = [({"bonds/j": good["bonds/i"].copy()}, "joins particle 0 to 0"),
                 ({k: np.concatenate([good[k], good[k]]) for k in good if k.startswith("bonds/")},
                  "list a pair of particles twice"),
                 ({"bonds/area": np.zeros(1)}, "bonds/area holds values that are not positive"),
                 ({"particles/layer": np.array([0, 2**40 + 7])}, "particles/layer holds values "
                                                                 "above 2147483647")]
        for change, words in cases:
            with pytest.raises(ValueError, match=words):
                sim.load_state_dict({**good, **change})
        moved = {**good, "particles/x": good["particles/x"] + 0.01,
                 "particles/sample_index": np.zeros(2, np.int32)}
        with pytest.raises(ValueError, match="sample_index of system 0"):
            sim.load_state_dict(moved)
        np.testing.assert_array_equal(sim.positions(), good["particles/x"])
    finally:
        sim.close()


def test_wall_directions_of_huge_components_and_ignored_frequencies():
    """(1e300, 1e300, 0) became the direction (0, 0, 0) (its norm overflowed); a constant
    motion's frequency was ignored without a word; the warnings pointed into tcd's files."""
    assert walls.plane((0, 0, 0), (1e300, 1e300, 0)).direction == pytest.approx(
        (2 ** -0.5, 2 ** -0.5, 0.0))
    # an ordinary normal is normalised as before, to the last bit (a rescaled vector is not)
    d = np.array([np.sin(0.3), 0.0, np.cos(0.3)])
    assert walls.plane((0, 0, 0), d).direction == tuple(float(c) for c in d / np.linalg.norm(d))
    with pytest.warns(UserWarning, match="ignores its frequency") as record:
        walls.plane((0, 0, 0), (0, 0, 1), motion="constant", frequency=-5)
    assert record[0].filename == __file__
    with pytest.warns(RuntimeWarning, match="behind it") as record:
        Simulation([1e-3], [[0, 0, -0.1]], walls=[walls.plane((0, 0, 0), (0, 0, 1))]).close()
    assert record[0].filename == __file__


def test_api_misuse_is_a_message_not_numpy_s():
    sim = _pair()
    try:
        for bad in (0.5, True):
            with pytest.raises(TypeError, match="integer index"):
                sim.system_slice(bad)
        with pytest.raises(TypeError, match="load_state_dict takes a state_dict"):
            sim.load_state_dict(None)
    finally:
        sim.close()
    with pytest.raises(TypeError, match="needs the radii and the positions"):
        Simulation(None, [[0, 0, 0]])
    Simulation([1e-3], [[0, 0, 0.1]], walls=None).close()      # None: no walls


def test_a_value_set_in_place_of_a_stage_table_is_one_line(tmp_path, capsys):
    """`--set 'stage[1]=1'` (or a string, an array) put a value into the array of stage tables,
    which tomlkit then failed to write: a traceback, exit 1 (session 72's review)."""
    path = _cli_scenario(tmp_path)
    for value in ("1", '"x"', "[1]"):
        assert main(["info", str(path), "--set", f"stage[1]={value}"]) == 2, value
        err = capsys.readouterr().err
        assert "stage[1] is a [[stage]] table: set one of its keys" in err, err
        assert err.count("\n") == 1, err
