"""The `tcd` command: exit codes, messages, refusal to overwrite, arguments handed to the
modules that do the work (stubbed here: no simulation runs)."""
import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

import tcd
from conftest import run_tcd
from tcd import io
from tcd.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]

SCENARIO = """\
name = "cli-test"

[[stage]]
kind = "prepare"
particles_per_layer = 10

[[stage]]
kind = "shear"
"""


@pytest.fixture
def scenario_file(tmp_path):
    path = tmp_path / "cli.toml"
    path.write_text(SCENARIO)
    return path


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"tcd {tcd.__version__}"


def test_unknown_subcommand_and_bad_flag_exit_2(capsys):
    assert main(["explode"]) == 2
    assert main(["run"]) == 2                   # missing SCENARIO
    assert main(["run", "x.toml", "--arch", "tpu"]) == 2
    assert "invalid choice" in capsys.readouterr().err


def test_run_missing_scenario(tmp_path, capsys, runner_calls):
    missing = tmp_path / "missing.toml"
    assert main(["run", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tcd: error: ") and str(missing) in err and "no such" in err
    assert runner_calls == []


def test_run_bad_scenario_names_the_key(tmp_path, capsys, runner_calls):
    bad = tmp_path / "bad.toml"
    bad.write_text(SCENARIO + "[solver]\ntime_step = -1\n")
    assert main(["run", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tcd: error: ")
    assert f"{bad}: solver.time_step: must be greater than or equal to" in err
    assert "Traceback" not in err and runner_calls == []


def test_run_passes_scenario_overrides_and_default_out_dir(scenario_file, tmp_path, monkeypatch,
                                                           capsys, runner_calls):
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(scenario_file), "--arch", "gpu", "--precision", "f32"]) == 0
    (call,) = runner_calls
    assert call["scenario"].name == "cli-test"
    assert (call["scenario"].backend.arch, call["scenario"].backend.precision) == ("gpu", "f32")
    assert str(call["out_dir"]) == "runs/cli-test"
    assert call["resume"] is False and call["progress"] is True and call["jobs"] == 1
    out = capsys.readouterr().out
    assert "runs/cli-test" in out and "0.837123" in out


def test_run_passes_jobs_and_refuses_zero(scenario_file, tmp_path, capsys, runner_calls):
    assert main(["run", str(scenario_file), "--out", str(tmp_path / "o"), "--jobs", "2"]) == 0
    assert runner_calls[0]["jobs"] == 2
    assert main(["run", str(scenario_file), "--out", str(tmp_path / "p"), "--jobs", "0"]) == 2
    assert "positive integer" in capsys.readouterr().err and len(runner_calls) == 1


def test_run_refuses_to_overwrite_results(scenario_file, tmp_path, capsys, runner_calls):
    out_dir = tmp_path / "done"
    out_dir.mkdir()
    (out_dir / "summary.json").write_text("{}")
    assert main(["run", str(scenario_file), "--out", str(out_dir)]) == 2
    err = capsys.readouterr().err
    assert "summary.json" in err and "--resume" in err and "--out" in err
    assert runner_calls == []
    assert (out_dir / "summary.json").read_text() == "{}"


def test_run_refuses_a_directory_with_a_checkpoint(scenario_file, tmp_path, capsys, runner_calls):
    out_dir = tmp_path / "half"
    (out_dir / "sample_1").mkdir(parents=True)
    (out_dir / "sample_1" / "checkpoint.h5").write_bytes(b"")
    assert main(["run", str(scenario_file), "--out", str(out_dir)]) == 2
    assert "checkpoint.h5" in capsys.readouterr().err and runner_calls == []


def test_run_into_an_empty_existing_directory_is_fine(scenario_file, tmp_path, runner_calls):
    out_dir = tmp_path / "empty"
    out_dir.mkdir()
    assert main(["run", str(scenario_file), "--out", str(out_dir)]) == 0
    assert runner_calls[0]["out_dir"] == out_dir


def test_resume_is_passed_to_the_runner(scenario_file, tmp_path, runner_calls):
    out_dir = tmp_path / "half"
    out_dir.mkdir()
    (out_dir / "summary.json").write_text("{}")
    assert main(["run", str(scenario_file), "--out", str(out_dir), "--resume"]) == 0
    assert runner_calls[0]["resume"] is True


def test_resume_without_a_run_directory(scenario_file, tmp_path, capsys, runner_calls):
    assert main(["run", str(scenario_file), "--out", str(tmp_path / "none"), "--resume"]) == 2
    assert "nothing to resume" in capsys.readouterr().err and runner_calls == []


def test_resume_without_checkpoint_reports_the_runner_message(scenario_file, tmp_path, capsys,
                                                              stub):
    def run_scenario(scenario, out_dir, *, resume=False, progress=True, jobs=1):
        raise FileNotFoundError(f"{out_dir}: nothing to resume (no checkpoint found)")
    stub("runner", run_scenario=run_scenario)
    (tmp_path / "empty").mkdir()
    assert main(["run", str(scenario_file), "--out", str(tmp_path / "empty"), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tcd: error: ") and "no checkpoint found" in err


def test_interrupted_run_says_how_to_resume(scenario_file, tmp_path, capsys, stub):
    def run_scenario(scenario, out_dir, *, resume=False, progress=True, jobs=1):
        raise KeyboardInterrupt
    stub("runner", run_scenario=run_scenario)
    out_dir = tmp_path / "run"
    assert main(["run", str(scenario_file), "--out", str(out_dir), "--arch", "cpu"]) == 130
    err = capsys.readouterr().err
    assert "interrupted; resume with: tcd run" in err
    assert f"--out {out_dir}" in err and "--arch cpu" in err and err.rstrip().endswith("--resume")


def test_seeds_option_runs_a_subset_and_the_resume_advice_repeats_it(tmp_path, capsys, stub):
    calls = []

    def run_scenario(scenario, out_dir, *, resume=False, progress=True, jobs=1):
        calls.append(scenario.seeds)
        raise KeyboardInterrupt
    stub("runner", run_scenario=run_scenario)
    path = tmp_path / "five.toml"
    path.write_text("seeds = [1, 2, 3, 4, 5]\n" + SCENARIO)
    out_dir = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out_dir), "--seeds", "4,2", "--jobs", "2"]) == 130
    assert calls == [[4, 2]]
    err = capsys.readouterr().err
    assert "--seeds 4,2 --jobs 2 --resume" in err


def test_set_option_runs_the_scenario_with_those_keys_and_the_resume_repeats_them(
        tmp_path, capsys, stub):
    """`tcd run S --set KEY=VALUE ...`: the run gets the scenario with those keys set (a value
    read as TOML, a bare word as a string, a stage counted from 1), the file's comments kept and
    a first line naming the settings; the file itself is not touched; an interruption's resume
    command repeats them."""
    from tcd import config
    got = []

    def run_scenario(scenario, out_dir, *, resume=False, progress=True, jobs=1):
        got.append(scenario)
        raise KeyboardInterrupt
    stub("runner", run_scenario=run_scenario)
    path = tmp_path / "five.toml"
    text = "# the study\nseeds = [1, 2, 3]\n" + SCENARIO.replace(
        'kind = "shear"', 'kind = "shear"\ndisplacement_mm = 2.5   # the paper\'s')
    path.write_text(text)
    out_dir = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out_dir), "--set", "bond.yield_stress_MPa=1.6",
                 "--set", "solver.tolerance=1e-6", "--set", "solver.sweep_order=forward",
                 "--set", "stage[2].displacement_mm=1.0", "--set", "seeds=[2, 3]"]) == 130
    (scenario,) = got
    assert scenario.bond.yield_stress_MPa == 1.6 and scenario.solver.tolerance == 1e-6
    assert scenario.solver.sweep_order == "forward" and scenario.seeds == (2, 3)
    assert scenario.stages[1].displacement_mm == 1.0
    assert scenario.stages[0].particles_per_layer == 10       # the rest as written
    assert "# the study\n" in scenario.text and "displacement_mm = 1.0   # the paper's" in scenario.text
    assert scenario.text.startswith(config.SETTINGS_HEADER + "--set bond.yield_stress_MPa=1.6 ")
    assert config.text_settings(scenario.text).endswith("--set 'seeds=[2, 3]'")
    assert config.parse_scenario(scenario.text, str(path)) == scenario      # what workers read
    assert path.read_text() == text
    err = capsys.readouterr().err
    assert ("--set bond.yield_stress_MPa=1.6 --set solver.tolerance=1e-6 --set "
            "solver.sweep_order=forward --set 'stage[2].displacement_mm=1.0' --set 'seeds=[2, 3]' "
            "--resume") in err, err


@pytest.mark.parametrize("setting, message", [
    ("bond.yeild_stress_MPa=1.6", "bond.yeild_stress_MPa: unknown key (did you mean 'yield_stress_MPa'?)"),
    ("solver.tolerance=-1", "solver.tolerance: must be greater than 0"),
    ("stage[3].displacement_mm=1", "stage[3].displacement_mm: --set: no stage[3]: the scenario has 2 [[stage]] tables"),
    ("stage.displacement_mm=1", "stage.displacement_mm: --set: stage holds [[stage]] tables: name one as stage[K]"),
    ("name.x=1", "name.x: --set: name is a value, not a table"),
    ("tolerance", "expected KEY=VALUE"),
    ("stage[0].x=1", "is not a scenario key"),
])
def test_set_option_names_what_cannot_be_set(scenario_file, tmp_path, capsys, runner_calls,
                                             setting, message):
    assert main(["run", str(scenario_file), "--out", str(tmp_path / "run"), "--set", setting]) == 2
    assert message in capsys.readouterr().err and runner_calls == []
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("seeds, message", [("9", "[9] not among the scenario's seeds"),
                                             ("2,2", "repeats a seed"),
                                             ("x", "comma-separated integer seeds")])
def test_seeds_option_rejects_seeds_the_scenario_lacks(tmp_path, capsys, runner_calls, seeds, message):
    path = tmp_path / "five.toml"
    path.write_text("seeds = [1, 2, 3, 4, 5]\n" + SCENARIO)
    assert main(["run", str(path), "--out", str(tmp_path / "run"), "--seeds", seeds]) == 2
    assert message in capsys.readouterr().err and runner_calls == []
    assert not (tmp_path / "run").exists()


def test_info_missing_file(tmp_path, capsys):
    assert main(["info", str(tmp_path / "missing.h5")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tcd: error: ") and "missing.h5" in err


def test_info_not_hdf5(tmp_path, capsys):
    path = tmp_path / "notes.h5"
    path.write_text("not hdf5")
    assert main(["info", str(path)]) == 2
    assert "notes.h5" in capsys.readouterr().err


@pytest.mark.parametrize("argv, expected", [
    (["pour", "--particles", "300", "--time", "0.1"],
     ("pour", dict(particles=300, time=0.1, arch="cpu", precision="f64", tolerance=1e-4, seed=1,
                   schedule="auto", threads=2, colouring="auto", check_every=1))),
    (["shear", "--precision", "f32", "--seed", "7", "--tolerance", "1e-3", "--schedule",
      "partitioned", "--threads", "4"],
     ("shear", dict(particles=5200, arch="cpu", precision="f32", tolerance=1e-3, seed=7,
                    schedule="partitioned", threads=4, colouring="auto", check_every=1))),
    (["scaling", "--sizes", "100,200", "--steps", "5", "--out", "x", "--schedule", "coloured",
      "--colouring", "rounds"],
     ("scaling", dict(sizes=[100, 200], steps=5, arch="cpu", precision="f64", tolerance=1e-4,
                      out="x", schedule="coloured", threads=2, colouring="rounds", settle=0.3,
                      check_every=1))),
    (["scaling", "--sizes", "1000000", "--steps", "10", "--settle", "0.05"],
     ("scaling", dict(sizes=[1000000], steps=10, arch="cpu", precision="f64", tolerance=1e-4,
                      out="renders/scaling", schedule="auto", threads=2, colouring="auto",
                      settle=0.05, check_every=1))),
    (["pour", "--sweep-order", "forward"],
     ("pour", dict(particles=2600, arch="cpu", precision="f64", tolerance=1e-4, seed=1,
                   schedule="auto", threads=2, colouring="auto", check_every=1,
                   sweep_order="forward"))),
    (["shear", "--warm-start-extrapolation", "0.5"],
     ("shear", dict(particles=5200, arch="cpu", precision="f64", tolerance=1e-4, seed=1,
                    schedule="auto", threads=2, colouring="auto", check_every=1,
                    warm_start_extrapolation=0.5))),
    (["shear", "--schedule", "resident", "--acceleration", "none"],
     ("shear", dict(particles=5200, arch="cpu", precision="f64", tolerance=1e-4, seed=1,
                    schedule="resident", threads=2, colouring="auto", check_every=1,
                    acceleration="none"))),
    (["scaling", "--sizes", "1000", "--acceleration", "none"],
     ("scaling", dict(sizes=[1000], steps=200, arch="cpu", precision="f64", tolerance=1e-4,
                      out="renders/scaling", schedule="auto", threads=2, colouring="auto",
                      settle=0.3, check_every=1, acceleration="none"))),
    (["shear", "--renumber"],
     ("shear", dict(particles=5200, arch="cpu", precision="f64", tolerance=1e-4, seed=1,
                    schedule="auto", threads=2, colouring="auto", check_every=1,
                    renumber=True))),
    (["pour", "--convergence", "quad", "--check-every", "5"],
     ("pour", dict(particles=2600, arch="cpu", precision="f64", tolerance=1e-4, seed=1,
                   schedule="auto", threads=2, colouring="auto", check_every=5,
                   convergence="quad"))),
    (["scaling", "--sizes", "1000", "--convergence", "quad"],
     ("scaling", dict(sizes=[1000], steps=200, arch="cpu", precision="f64", tolerance=1e-4,
                      out="renders/scaling", schedule="auto", threads=2, colouring="auto",
                      settle=0.3, check_every=1, convergence="quad"))),
    (["pour", "--trace", "t.csv"],
     ("pour", dict(particles=2600, arch="cpu", precision="f64", tolerance=1e-4, seed=1,
                   schedule="auto", threads=2, colouring="auto", check_every=1,
                   trace="t.csv"))),
    (["shear", "--bond-solve", "pairs", "--check-every", "4"],
     ("shear", dict(particles=5200, arch="cpu", precision="f64", tolerance=1e-4, seed=1,
                    schedule="auto", threads=2, colouring="auto", check_every=4,
                    bond_blocks=False))),
])
def test_bench_passes_keyword_options(argv, expected, stub, capsys):
    calls = []

    def recorder(name):
        def bench(**kwargs):
            if name == "scaling":       # a progress line per finished size
                assert callable(kwargs.pop("progress"))
            calls.append((name, kwargs))
            return {"benchmark": name, "seconds_per_particle_step": 1.25e-6, "bed": {"top": 0.1}}
        return bench
    stub("bench", pour=recorder("pour"), shear=recorder("shear"), scaling=recorder("scaling"))
    assert main(["bench"] + argv + ["--json"]) == 0
    assert calls == [expected]
    printed = json.loads(capsys.readouterr().out)
    assert printed["benchmark"] == expected[0] and printed["bed"]["top"] == 0.1
    assert main(["bench"] + argv) == 0          # table form: one dotted key per line
    table = capsys.readouterr().out
    assert "seconds_per_particle_step  1.25e-06" in table and "bed.top" in table


def test_bench_json_stdout_holds_the_json_alone(stub, capsys):
    """Whatever is printed during the run (Taichi's start-up banner) goes to stderr, so that
    `tcd bench ... --json | jq` works."""
    def pour(**kwargs):
        print("[Taichi] Starting on arch=x64")
        return {"benchmark": "pour", "seconds_per_particle_step": 1e-5}
    stub("bench", pour=pour)
    assert main(["bench", "pour", "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["seconds_per_particle_step"] == 1e-5
    assert "[Taichi] Starting" in err


def test_bench_repeat_reports_the_median_run(stub, capsys):
    figures = iter([3e-6, 1e-6, 2e-6])
    calls = []

    def pour(**kwargs):
        calls.append(kwargs)
        value = next(figures)
        return {"benchmark": "pour", "seconds_per_particle_step": value, "run": value}
    stub("bench", pour=pour)
    assert main(["bench", "pour", "--particles", "50", "--repeat", "3", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert len(calls) == 3 and all(c == calls[0] for c in calls)
    assert printed["seconds_per_particle_step"] == 2e-6 and printed["run"] == 2e-6
    assert printed["repeats"] == 3
    assert printed["repeats_seconds_per_particle_step"] == [3e-6, 1e-6, 2e-6]
    assert main(["bench", "pour", "--repeat", "0"]) == 2
    # every run would overwrite one trace: refused before any run
    assert main(["bench", "pour", "--repeat", "3", "--trace", "t.csv"]) == 2
    assert len(calls) == 3 and "--trace with --repeat" in capsys.readouterr().err


def test_bench_table_prints_one_row_per_phase(stub, capsys):
    def pour(**kwargs):
        return {"benchmark": "pour", "phases": [{"time_s": [0.0, 0.5], "mean_sweeps": 2.5},
                                                {"time_s": [0.5, 1.0], "mean_sweeps": 900.0}]}
    stub("bench", pour=pour)
    assert main(["bench", "pour"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(l.startswith("phases[0]") and "time_s=0, 0.5; mean_sweeps=2.5" in l for l in lines)
    assert any(l.startswith("phases[1]") and "mean_sweeps=900" in l for l in lines)


def test_table_flattens_nested_items_into_dotted_rows():
    """A run's summary holds a list of samples, each with nested stages: every number gets a row
    of its own, written as a number (not the repr of a nested dict or of a NumPy scalar)."""
    import numpy as np
    from tcd.cli import format_table
    table = format_table({"samples": [{"seed": 2, "stages": {"0:prepare": {
        "coordination_number": np.float64(5.310910022195663), "layer_heights_mm": [55.78, 64.22]}},
        "walls": [{"name": "top plate", "friction": 0.3}]}]})
    rows = dict(line.split(None, 1) for line in table.splitlines())
    assert rows["samples[0].seed"] == "2"
    assert rows["samples[0].stages.0:prepare.coordination_number"] == "5.31091"
    assert rows["samples[0].stages.0:prepare.layer_heights_mm"] == "55.78, 64.22"
    assert rows["samples[0].walls[0]"] == "name=top plate; friction=0.3"
    assert "np.float64" not in table and "{" not in table


def test_render_initialises_the_backend_and_passes_options(tmp_path, stub, backend, monkeypatch):
    arch, precision = backend
    states = tmp_path / "states.h5"
    states.write_bytes(b"")
    calls = []
    stub("render", WriterMissing=type("WriterMissing", (RuntimeError,), {}),
         render_file=lambda path, out, **kw: calls.append((path, out, kw)),
         check_output=lambda out, frame=-1: calls.append(("checked", out, frame)))
    inits = []
    monkeypatch.setattr(tcd, "init", lambda a, p: inits.append((a, p)))
    assert main(["render", str(states), "--out", str(tmp_path / "a.gif"), "--frames", "0,2",
                 "--color", "speed", "--section", "xz", "--camera", "front", "--width", "64",
                 "--height", "48", "--arch", arch, "--precision", precision]) == 0
    assert inits == [(arch, precision)]
    assert calls[0] == ("checked", str(tmp_path / "a.gif"), -1)
    (path, out, kw) = calls[1]
    assert str(path) == str(states) and str(out) == str(tmp_path / "a.gif")
    assert kw == dict(frame=-1, frames=[0, 2], color="speed", section="xz", camera="front",
                      width=64, height=48, fps=10.0)


def test_figures_prints_written_files(tmp_path, stub, capsys):
    asked = []
    stub("figures", make_figures=lambda run_dir, out_dir=None, velocity="mean":
         asked.append(velocity) or [tmp_path / "fig1.png"])
    assert main(["figures", str(tmp_path)]) == 0
    assert str(tmp_path / "fig1.png") in capsys.readouterr().out
    assert main(["figures", str(tmp_path), "--velocity", "instant"]) == 0
    assert asked == ["mean", "instant"]                 # Fig. 3: the mean velocity by default
    assert main(["figures", str(tmp_path), "--velocity", "average"]) == 2
    assert "invalid choice: 'average'" in capsys.readouterr().err
    assert main(["figures", str(tmp_path / "nope")]) == 2
    # several run directories (one study split with --seeds): all are passed, --out is needed
    stub("figures", make_figures=lambda run_dir, out_dir=None, velocity="mean":
         [pathlib.Path(out_dir) / "table2.md"])
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    assert main(["figures", str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    assert "give --out" in capsys.readouterr().err
    assert main(["figures", str(tmp_path / "a"), str(tmp_path / "b"), "--out",
                 str(tmp_path / "o")]) == 0
    assert str(tmp_path / "o" / "table2.md") in capsys.readouterr().out


def test_view_without_display_exits_2(tmp_path, stub, capsys):
    def view(path, **kw):
        raise RuntimeError("the interactive viewer needs a display")
    stub("viewer", view=view)
    states = tmp_path / "states.h5"
    states.write_bytes(b"")
    assert main(["view", str(states)]) == 2
    assert "needs a display" in capsys.readouterr().err


def test_cli_and_config_import_no_heavy_module():
    heavy = ("tcd.runner", "tcd.render", "tcd.simulation", "tcd.viewer", "tcd.bench",
             "tcd.figures", "pydantic")
    code = ("import sys\n"
            "def loaded(): return ','.join(m for m in %r if m in sys.modules)\n"
            "import tcd.cli; print(loaded())\n"
            "import tcd.config; print(loaded())\n" % (heavy,))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout.splitlines()
    assert out[-2] == ""                 # the command's module: nothing until a handler runs
    assert out[-1] == "pydantic"         # the configuration: pydantic, not the solver


def _gpu_present() -> bool:
    from taichi.lang.misc import is_arch_supported
    import taichi as ti
    return any(is_arch_supported(getattr(ti, name)) for name in tcd.backend.GPU_ARCHS)


def test_gpu_backend_search_never_probes_opengl(monkeypatch):
    """arch='gpu' tries CUDA, Vulkan, Metal and AMDGPU in turn and never OpenGL (Taichi's probe
    of OpenGL kills a headless process with a segmentation fault: `ti.init(arch=ti.gpu)` on a
    machine without a GPU did); none found is a BackendUnavailable naming what was tried."""
    import taichi as ti
    import taichi.lang.misc as misc
    probed = []

    def supported_only(found):
        def probe(arch):
            probed.append(arch)
            return arch in found
        return probe
    monkeypatch.setattr(misc, "is_arch_supported", supported_only({ti.vulkan}))
    assert tcd.backend.gpu_arch() == ti.vulkan
    assert probed == [ti.cuda, ti.vulkan]
    probed.clear()
    monkeypatch.setattr(misc, "is_arch_supported", supported_only(set()))
    with pytest.raises(tcd.backend.BackendUnavailable, match="no GPU backend.*cuda, vulkan, metal, amdgpu"):
        tcd.backend.gpu_arch()
    assert ti.opengl not in probed and len(probed) == len(tcd.backend.GPU_ARCHS)


def test_init_raises_the_kernel_cache_limit_unless_the_environment_sets_it(backend):
    """tcd.init gives Taichi's offline kernel cache 1 GiB instead of its 100 MB (one run of the
    test suite compiles about 96 MB: at 100 MB runs evicted each other's kernels); the
    environment variable TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES, when set, is Taichi's to apply."""
    import os
    import taichi as ti
    limit = ti.lang.impl.current_cfg().offline_cache_max_size_of_files
    env = os.environ.get("TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES")
    if env:
        assert limit == int(env)
    else:
        assert limit == tcd.backend.OFFLINE_CACHE_BYTES > 100 * 2**20


@pytest.mark.parametrize("command", [["bench", "pour", "--particles", "10", "--time", "0.001"],
                                     ["run", str(ROOT / "scenarios" / "tiny.toml")]])
def test_gpu_requested_without_a_gpu_is_a_clear_error_and_writes_nothing(command, tmp_path):
    """In a fresh process (Taichi not yet initialised), as a user runs it."""
    if _gpu_present():
        pytest.skip("this machine has a GPU backend")
    out = tmp_path / "run"
    extra = ["--out", str(out)] if command[0] == "run" else []
    proc = subprocess.run([sys.executable, "-m", "tcd.cli", *command, *extra, "--arch", "gpu"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "tcd: error: arch 'gpu' requested but Taichi found no GPU backend" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not out.exists()


SAMPLE = ROOT / "samples" / "leutner_seed1_prepared.h5"


def test_analyse_never_overwrites_its_input_and_takes_a_prefix_with_its_suffix(tmp_path, capsys):
    src = tmp_path / "states.h5"
    src.write_bytes(SAMPLE.read_bytes())
    assert main(["analyse", str(src), "--out", str(tmp_path / "states")]) == 2
    assert "would overwrite the file being analysed" in capsys.readouterr().err
    assert src.read_bytes() == SAMPLE.read_bytes()
    assert main(["analyse", str(src), "--out", str(tmp_path / "micro.h5"), "--time-step", "2e-4"]) == 0
    assert (tmp_path / "micro.h5").is_file() and (tmp_path / "micro.csv").is_file()
    assert not (tmp_path / "micro.h5.h5").exists()


def test_damaged_files_and_unwritable_outputs_are_one_line_naming_the_file(tmp_path, capsys,
                                                                           monkeypatch):
    damaged = tmp_path / "damaged.h5"
    data = bytearray(SAMPLE.read_bytes())
    data[3000:4500] = bytes(range(256)) * 5 + bytes(220)       # inside the HDF5 metadata
    damaged.write_bytes(bytes(data))
    for command in (["info"], ["export", "--out", str(tmp_path / "vtk")],
                    ["analyse", "--out", str(tmp_path / "micro")]):
        assert main([command[0], str(damaged), *command[1:]]) == 2, command
        err = capsys.readouterr().err
        assert err.startswith(f"tcd: error: {damaged}") and "Traceback" not in err, err
    # an h5py error reported as RuntimeError or KeyError (a damaged group, a missing dataset)
    from tcd import io
    for exc in (RuntimeError("Unable to get group info (bad symbol table node signature)"),
                KeyError("particles/radius")):
        def broken(path, exc=exc):
            raise exc
        monkeypatch.setattr(io, "info", broken)
        assert main(["info", str(SAMPLE)]) == 2
        assert f"tcd: error: {SAMPLE}: cannot read ({type(exc).__name__}" in capsys.readouterr().err
    monkeypatch.undo()
    # the output is at fault, not the input
    assert main(["export", str(SAMPLE), "--out", "/proc/no/such/dir"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tcd: error: /proc/no") and "cannot write" in err, err


def test_info_into_a_closed_pipe_stops_quietly():
    """`tcd info FILE | head`: more output than the pipe holds (a long states file's)."""
    code = ("import tcd.io as io; io.info = lambda path: 'line\\n' * 200000; "
            f"from tcd.cli import main; raise SystemExit(main(['info', {str(SAMPLE)!r}]))")
    proc = subprocess.run(f"{sys.executable} -c \"{code}\" | head -1", shell=True,
                          capture_output=True, text=True, timeout=120, executable="/bin/bash")
    assert proc.stdout == "line\n"
    assert "Broken pipe" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr


@pytest.mark.parametrize("out, message", [("picture", "the extension sets the format"),
                                          ("picture.xyz", "the extension sets the format"),
                                          ("folder.png", "is a directory")])
def test_render_refuses_an_output_it_cannot_write_before_it_starts(tmp_path, capsys, out, message):
    (tmp_path / "folder.png").mkdir()
    assert main(["render", str(SAMPLE), "--out", str(tmp_path / out)]) == 2
    assert message in capsys.readouterr().err


def test_repeated_frames_and_parts_are_exported_once(tmp_path, capsys):
    """--parts particles,particles reported 2 files written for 1 (and a .pvd listed the file
    twice)."""
    assert main(["export", str(SAMPLE), "--out", str(tmp_path / "vtk"), "--parts",
                 "particles,particles", "--frames", "0,0"]) == 0
    assert "wrote 1 VTK files" in capsys.readouterr().out
    pvd = (tmp_path / "vtk" / f"{SAMPLE.stem}_particles.pvd").read_text()
    assert pvd.count("<DataSet ") == 1


def test_negative_frames_count_from_the_end_as_the_help_says(tmp_path, capsys):
    """`--frames -1` was taken by argparse for an option ("expected one argument"), and -1
    and N-1 were exported as two frames."""
    from tcd.cli import _joined_frames
    assert _joined_frames(["export", "f.h5", "--frames", "-1,-2", "--out", "v"]) == [
        "export", "f.h5", "--frames=-1,-2", "--out", "v"]
    assert _joined_frames(["export", "--frames", "--out"]) == ["export", "--frames", "--out"]
    states = tmp_path / "states.h5"
    x = np.array([[0.0, 0.0, 0.01]])
    for k in range(3):
        io.append_frame(states, {"particles/x": x + k, "particles/radius": np.array([0.005])},
                        time=0.1 * k, step=k, stage="pour")
    assert main(["export", str(states), "--out", str(tmp_path / "v"), "--parts", "particles",
                 "--frames", "-1,2,-3"]) == 0
    assert "wrote 2 VTK files" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "v").glob("*.vtu")) == [
        "states_particles_000000.vtu", "states_particles_000002.vtu"]
    # a later export of fewer frames into the same folder says the older files are there
    assert main(["export", str(states), "--out", str(tmp_path / "v"), "--parts", "particles",
                 "--frames", "-2"]) == 0
    err = capsys.readouterr().err
    assert "2 .vtu files of an earlier export are also in" in err


def test_frame_with_an_animation_output_is_refused(tmp_path, capsys):
    assert main(["render", str(SAMPLE), "--out", str(tmp_path / "a.gif"), "--frame", "2"]) == 2
    assert "an animation" in capsys.readouterr().err and not (tmp_path / "a.gif").exists()


def test_shear_of_a_sample_file_farther_than_its_diameter_is_refused(tmp_path, capsys):
    """The mould's diameter of a sample file is known once the file is read: a displacement
    at least as large (the upper ring would leave the lower one) stops the run with one line
    naming the key and the file, before anything is written (since session 42, when every
    seed's sample is checked before the first runs)."""
    scenario = tmp_path / "far.toml"
    scenario.write_text(f'name = "far"\n[[stage]]\nkind = "shear"\nsample = "{SAMPLE}"\n'
                        'displacement_mm = 200.0\nvelocity_mm_per_min = 60000.0\n')
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"tcd: error: {SAMPLE} (seed 1): shear displacement_mm 200 mm is not smaller than " \
           "the sample's 150 mm diameter" in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


def test_a_grid_too_large_for_the_grains_names_the_scenario_keys_to_change(tmp_path, capsys):
    """Tiny grains in a tall, wide column make a broad-phase grid of 2e10 cells: the refusal
    named `cell_size`, which no scenario has (session 42 audit); it now names the keys."""
    text = (ROOT / "scenarios" / "tiny.toml").read_text()
    for key, value in (("size_scale", "0.01"), ("column_height_mm", "2000.0"),
                       ("cylinder_diameter_mm", "100.0"), ("particles_per_layer", "20")):
        text, n = __import__("re").subn(rf"(?m)^{key} = .*$", f"{key} = {value}", text)
        assert n == 1, key
    scenario = tmp_path / "fine.toml"
    scenario.write_text(text)
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"tcd: error: {scenario}: broad-phase grid of" in err and "Traceback" not in err
    assert "column_height_mm or cylinder_diameter_mm, or raise its size_scale" in err


# --- session 43's mutation audit of the walls, the API, the benchmarks and the renderer -------
def test_repeat_reports_the_median_run_not_the_mean():
    """--repeat N reports the median run whole (its figure and its other fields), not the mean
    of the figures: with one slow outlier the two differ (the CLI test's 3, 1, 2 had mean ==
    median)."""
    from tcd.cli import median_run
    figures = iter([9e-6, 1e-6, 2e-6])

    def run(**kw):
        value = next(figures)
        return {"seconds_per_particle_step": value, "run": value}
    out = median_run(run, {}, 3)
    assert out["seconds_per_particle_step"] == 2e-6 and out["run"] == 2e-6
    assert out["repeats_seconds_per_particle_step"] == [9e-6, 1e-6, 2e-6]



def test_every_module_of_the_package_is_reachable_after_a_plain_import_tcd():
    """docs/scripting.md writes tcd.io.append_frame, tcd.runner...: after `import tcd` alone
    they were AttributeErrors (session 44's API audit). A fresh interpreter, as a script has."""
    package = pathlib.Path(tcd.__file__).parent
    modules = sorted(p.stem for p in package.glob("*.py") if not p.stem.startswith("__"))
    code = ("import tcd\n"
            f"print(all(getattr(tcd, m).__name__ == 'tcd.' + m for m in {modules!r}))\n"
            "print(tcd.io.append_frame.__name__, tcd.runner.run_lock.__name__, "
            "tcd.walls.plane.__name__)\n"
            "try:\n    tcd.no_such_module\nexcept AttributeError as exc:\n    print(exc)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines()[-3:] == ["True", "append_frame run_lock plane",
                                            "module 'tcd' has no attribute 'no_such_module'"]


# --- session 47's input fuzzing -------------------------------------------------------------------
def _damaged_sample(tmp_path, name, change):
    """A copy of the shipped sample with `change(h5py.File)` applied."""
    import h5py
    path = tmp_path / f"{name}.h5"
    path.write_bytes(SAMPLE.read_bytes())
    with h5py.File(path, "a") as f:
        change(f)
    return path


def _set(key, edit):
    def change(f):
        a = f[key][()]
        edit(a)
        del f[key]
        f[key] = a
    return change


def _set_meta(**values):
    def change(f):
        f.attrs["meta"] = json.dumps({**json.loads(f.attrs["meta"]), **values})
    return change


@pytest.mark.parametrize("name, change, words", [
    # a contact offset past the contact list: the warm start read it out of bounds and the
    # run died of a segmentation fault, after writing run.json and a states.h5
    ("start", _set("arrays/contacts/start", lambda a: a.__setitem__(5, 2**30)),
     "contacts/start is not a non-decreasing table"),
    ("start_negative", _set("arrays/contacts/start", lambda a: a.__setitem__(5, -7)),
     "contacts/start is not a non-decreasing table"),
    # a clock at 1e308 s: an OverflowError traceback at the first snapshot
    ("time", _set_meta(time=1e308), "time must be finite and within"),
])
def test_a_sample_that_would_crash_the_shear_is_refused_before_anything_is_written(
        tmp_path, capsys, name, change, words):
    sample = _damaged_sample(tmp_path, name, change)
    scenario = tmp_path / "s.toml"
    scenario.write_text(f'name = "s"\n[[stage]]\nkind = "shear"\nsample = "{sample}"\n')
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tcd: error: {sample}: ") and words in err, err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


def test_info_of_a_sample_with_a_damaged_mould_or_meta_is_a_summary_not_a_traceback(tmp_path,
                                                                                     capsys):
    """A mould of radius 0 divided by zero in the packing fraction; a `meta` attribute that is
    a number made json.loads raise TypeError (session 47's fuzzing)."""
    for name, change in (("mould", _set("arrays/walls/radius", lambda a: a.fill(0.0))),
                         ("meta", lambda f: f.attrs.__setitem__("meta", 3))):
        path = _damaged_sample(tmp_path, name, change)
        assert main(["info", str(path)]) == 0, name
        assert "tcd checkpoint file" in capsys.readouterr().out


def test_export_of_a_frame_lacking_a_part_writes_nothing(tmp_path, capsys):
    """A states frame without walls/point: the particles', contacts' and bonds' files of the
    frame were written before the walls' mesh failed (session 47's fuzzing)."""
    import h5py
    states = _one_frame_states(tmp_path)
    with h5py.File(states, "a") as f:
        del f["frames/000000/walls/point"]
    out = tmp_path / "vtk"
    assert main(["export", str(states), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tcd: error: {states}") and "walls/point" in err, err
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("argv, words", [
    # an OverflowError traceback from NumPy
    (["pour", "--particles", "99999999999999999999"], "--particles: expected at most 1e+07"),
    (["scaling", "--sizes", "99999999999999999999"], "--sizes '99999999999999999999': expected"),
    # "expected non-negative integer", from NumPy, named no option
    (["pour", "--seed", "-1"], "--seed: expected an integer >= 0, got -1"),
    # these ran for ever
    (["pour", "--time", "1e300"], "time 1e+300 s is more than 2.1e+09 time steps"),
    (["scaling", "--sizes", "300", "--steps", "99999999999999999999"], "at most 2147483647"),
    (["scaling", "--sizes", "300", "--steps", "3", "--settle", "1e300"],
     "settle 1e+300: expected a finite time >= 0 s, at most"),
])
def test_bench_options_out_of_range_are_one_line_naming_the_option(argv, words, capsys,
                                                                   tmp_path, monkeypatch):
    """Session 47's fuzzing of `tcd bench`: each is refused before a simulation is built."""
    monkeypatch.chdir(tmp_path)
    assert main(["bench", *argv]) == 2
    err = capsys.readouterr().err
    # (argparse's refusals print the usage first: the error is the last line)
    assert words in err.strip().splitlines()[-1] and "Traceback" not in err, err


def test_the_bench_particle_bound_is_the_scenarios_layer_bound():
    """The command line keeps its own copy (`tcd --help` imports nothing heavy)."""
    from tcd import bench, cli, config
    assert cli.MAX_BENCH_PARTICLES == bench.MAX_PARTICLES == config.MAX_PARTICLES_PER_LAYER


def _one_frame_states(tmp_path):
    """A states file of one frame: the shipped sample's arrays."""
    arrays, _ = io.load_checkpoint(SAMPLE)
    path = tmp_path / "states.h5"
    io.append_frame(path, {k: v for k, v in arrays.items() if k in io.FRAME_SCHEMA}, time=0.0,
                    step=0, stage="prepare")
    return path


def _states_with(tmp_path, key, edit):
    """`_one_frame_states`, its dataset `key` replaced by `edit(array)` in the file (as a
    damaged file holds it: append_frame would refuse it)."""
    import h5py
    path = _one_frame_states(tmp_path)
    with h5py.File(path, "a") as f:
        g = f["frames/000000"]
        value = edit(g[key][()])
        del g[key]
        g[key] = value
    return path


def _with(index, value):
    def edit(a):
        a[index] = value
        return a
    return edit


@pytest.mark.parametrize("key, edit, words", [
    # "sphere radii must be > 0 and positions finite": neither the file nor the key named
    ("particles/x", _with(0, np.nan), "key 'particles/x' holds 1 positions"),
    ("particles/radius", _with(0, -1e-3), "key 'particles/radius' holds 1 radii"),
    # NumPy's "operands could not be broadcast together ..."
    ("particles/x", lambda a: a[:, :2], "key 'particles/x' has shape"),
    # a layer id of 2**30 built a legend table of 2**30 rows: the render never ended
    ("particles/layer", _with(0, 2**30), "key 'particles/layer' holds the layer id"),
])
def test_render_refuses_a_damaged_frame_naming_the_file_and_key(tmp_path, key, edit, words):
    from tcd import render
    path = _states_with(tmp_path, key, edit)
    with pytest.raises(ValueError) as info:
        render.load_frame(path, 0)
    assert str(info.value).startswith(f"{path}: frame 000000: ") and words in str(info.value)


@pytest.mark.parametrize("option, value, words", [
    ("--width", "99999999999999999999", "--width: expected at most 16384 pixels"),   # traceback
    ("--height", "100000", "--height: expected at most 16384 pixels"),   # 67 GB allocation
    ("--fps", "1e-300", "--fps: expected a frame rate from 0.01 to 1000"),   # OverflowError
])
def test_render_sizes_and_rates_out_of_range_are_refused(tmp_path, capsys, option, value, words):
    assert main(["render", str(SAMPLE), "--out", str(tmp_path / "a.gif"), option, value]) == 2
    err = capsys.readouterr().err
    assert words in err.strip().splitlines()[-1] and "Traceback" not in err
    assert not (tmp_path / "a.gif").exists()


def test_a_sample_the_simulation_refuses_is_named_in_the_message(tmp_path, capsys):
    """Two grains at one centre are found when the sample's simulation is built: the message
    ("particles 0 and 1 have the same centre ...") did not say which file (session 47)."""
    def same_centre(a):
        a[1] = a[0]
        return a
    sample = _damaged_sample(tmp_path, "twins", _set("arrays/particles/x", same_centre))
    scenario = tmp_path / "s.toml"
    scenario.write_text(f'name = "s"\n[[stage]]\nkind = "shear"\nsample = "{sample}"\n')
    assert run_tcd(["run", str(scenario), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tcd: error: {sample}: ") and "same centre" in err, err


def test_run_warns_of_a_value_likely_in_another_unit_and_runs_it(tmp_path, capsys,
                                                                 runner_calls):
    path = tmp_path / "grams.toml"
    path.write_text(SCENARIO + "[material]\ndensity = 2.6\n")
    assert main(["run", str(path), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert f"tcd: warning: {path}: material.density: 2.6 kg/m^3" in err and "g/cm^3" in err
    assert runner_calls[0]["scenario"].material.density == 2.6


def test_a_run_with_set_keeps_its_settings_for_resume_and_info(tmp_path):
    """The run directory's scenario.toml is the scenario with the settings applied; a
    --resume without them is refused, naming the key; `tcd info` of the stopped run repeats
    them in its resume advice."""
    from tcd import config, runner
    path = tmp_path / "s.toml"
    path.write_text(SCENARIO)
    plain = config.load_scenario(path)
    setting = [config.parse_setting("bond.yield_stress_MPa=1.6")]
    scenario = config.load_scenario(path, setting)
    out = tmp_path / "run"
    runner.record_scenario(scenario, out, resume=False)
    assert (out / "scenario.toml").read_text() == scenario.text
    runner.record_scenario(config.load_scenario(path, setting), out, resume=True)   # the same
    with pytest.raises(ValueError, match=r"bond.yield_stress_MPa: 1.6 -> 2.7"):
        runner.record_scenario(plain, out, resume=True)
    # run.json names the scenario file: the advice gives it while it holds the run's scenario
    assert json.loads((out / "run.json").read_text())["scenario_file"] == str(path.resolve())
    info = runner.run_info(out)
    assert f"\nscenario file: {path.resolve()}\n" in info, info
    assert (f"resume it with `tcd run {path.resolve()} --out {out} --set "
            "bond.yield_stress_MPa=1.6 --resume`") in info, info
    path.write_text(SCENARIO.replace("particles_per_layer = 10", "particles_per_layer = 12"))
    info = runner.run_info(out)
    assert (f"scenario file: {path.resolve()}, changed since the run started "
            f"(stage[1].particles_per_layer: 10 -> 12): a --resume needs the run's scenario "
            f"({out / 'scenario.toml'}) back in a "
            "file") in info, info
    assert f"resume it with `tcd run <its scenario> --out {out} --set " in info, info
    path.unlink()
    info = runner.run_info(out)
    assert f"scenario file: {path.resolve()}, which cannot serve a --resume now (no such " in info
    assert f"resume it with `tcd run <its scenario> --out {out} --set " in info, info


def test_info_tells_the_samples_a_run_was_not_asked_for(tmp_path):
    """A run started with --seeds 2 of seeds 1-3: `tcd info` says the others were left out by
    --seeds, not merely that they have not started."""
    from tcd import config, runner
    path = tmp_path / "s.toml"
    path.write_text("seeds = [1, 2, 3]\n" + SCENARIO)
    out = tmp_path / "run"
    runner.record_scenario(config.load_scenario(path).with_seeds([2]), out, resume=False)
    assert json.loads((out / "run.json").read_text())["seeds"] == [2]
    info = runner.run_info(out)
    assert "\nsample_1: not started (the run began with --seeds 2)\n" in info, info
    assert "\nsample_2: not started\n" in info and "sample_3: not started (the run began" in info


def test_info_of_a_scenario_file_checks_it_and_lists_every_setting(tmp_path, capsys):
    """`tcd info SCENARIO.toml [--set ...]`: the scenario checked as `tcd run` would check it,
    nothing run: its seeds and stages, values likely in another unit, and every setting with
    the defaults filled in, those written in the file or by --set marked."""
    path = tmp_path / "s.toml"
    path.write_text("seeds = [1, 2]\n" + SCENARIO + "\n[bond]\nyield_stress_MPa = 2700\n")
    assert main(["info", str(path), "--set", "solver.tolerance=1e-6"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{path}: a valid tcd scenario 'cli-test': seeds 1, 2; stages "
                          "prepare, shear\n"), out
    assert "\nwarning: bond.yield_stress_MPa: 2700 MPa is above" in out, out
    lines = out.splitlines()
    row = {line[2:].split()[0]: (line[0], line[2:].split(None, 1)[1]) for line in lines
           if line[:2] in ("* ", "  ") and len(line[2:].split(None, 1)) == 2}
    assert row["bond.yield_stress_MPa"] == ("*", "2700")
    assert row["solver.tolerance"] == ("*", "1e-06")                # by --set
    assert row["stage[1].particles_per_layer"] == ("*", "10")
    assert row["solver.theta"][0] == " " and row["material.friction"] == (" ", "0.7")  # defaults
    assert main(["info", str(path), "--set", "bond.yeild=1"]) == 2
    assert "bond.yeild: unknown key" in capsys.readouterr().err
    assert main(["info", str(tmp_path), "--set", "bond.yield_stress_MPa=1"]) == 2
    assert "--set applies to a scenario file" in capsys.readouterr().err


def test_set_without_tomlkit_says_what_to_install(tmp_path, capsys, runner_calls, monkeypatch):
    """A checkout updated without reinstalling lacks tomlkit: --set says so, not a traceback."""
    path = tmp_path / "s.toml"
    path.write_text(SCENARIO)
    monkeypatch.setitem(sys.modules, "tomlkit", None)       # import tomlkit -> ImportError
    assert main(["run", str(path), "--out", str(tmp_path / "run"), "--set", "seeds=[1]"]) == 2
    assert "--set needs the tomlkit package" in capsys.readouterr().err and runner_calls == []


def test_info_of_a_scenario_gives_the_grains_a_preparation_makes():
    """The paper's preparation: the count per course from the size table at the packing
    fraction (README, "The five prepared samples": 1675 + 4182)."""
    from tcd import config
    text = config.describe(config.load_scenario(ROOT / "scenarios" / "leutner_prepare.toml"))
    assert ("stage[1] prepares 1675 + 4182 = 5857 grains a sample (courses binder, surface, "
            "bottom first)") in text, text
    text = config.describe(config.load_scenario(ROOT / "scenarios" / "leutner.toml"))
    assert ("stage[2] shears the sample prepared before it to 2.5 mm at 50 mm/min, 15000 time "
            "steps") in text, text             # the study's 15000 steps
