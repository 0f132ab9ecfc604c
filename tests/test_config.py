"""Scenario parsing: typed values and defaults, and one refusal per kind of bad input, each
naming the file, the key and the reason."""
import pathlib
import re

import pydantic
import pytest

from tcd.config import (BackendConfig, PrepareStage, ScenarioError, ShearStage,
                        load_scenario, parse_scenario)
from tcd.simulation import SolverSettings

ROOT = pathlib.Path(__file__).resolve().parents[1]

FULL = """\
name = "leutner-full"
description = "every key set"
seeds = [3, 1, 4]

[backend]
arch = "gpu"
precision = "f32"

[solver]
time_step = 1e-4
theta = 0.75
tolerance = 1e-5
max_sweeps = 500
check_every = 5
schedule = "coloured"
alert_ratio = 0.2
gravity = 9.8
colouring = "rounds"
sweep_order = "forward"
warm_start_extrapolation = 0.5
convergence = "quad"

[material]
density = 2500
friction = 0.6
wall_friction = 0.1

[bond]
mode = "burgers"
maxwell_stiffness = 3e6
maxwell_viscosity = 4e7
kelvin_stiffness = 5e6
kelvin_viscosity = 6e7
poisson_ratio = 0.25
yield_stress_MPa = 1.5
gap_tolerance_mm = 0.02
friction_after_break = 0.5

[output]
snapshot_every = 0.1
checkpoint_every_s = 30
series_every = 2

[[stage]]
kind = "prepare"
cylinder_diameter_mm = 100.0
layer_height_mm = 40.0
packing_fraction = 0.6
courses = ["binder", "surface", "surface"]
particles_per_layer = 500
size_scale = 0.5
column_height_mm = 800.0
lattice_jitter_mm = 0.1
settle_speed = 0.01
max_settle_time = 2.0
vibration_amplitude_mm = 3.0
vibration_frequency = 25.0
vibration_duration = 0.5
sample_height_mm = 110.0

[[stage]]
kind = "shear"
displacement_mm = 2.0
velocity_mm_per_min = 60.0
ring_height_mm = 55.0
gap_mm = 2.0
wall_friction = 0.2
smoothing_window_mm = 0.2
bond_mode = "paper"
"""

MINIMAL = """\
name = "tiny"

[[stage]]
kind = "prepare"

[[stage]]
kind = "shear"
"""


def write(tmp_path, text, name="scenario.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def refusal(tmp_path, text) -> ScenarioError:
    """The ScenarioError for `text` loaded from a file (so the message must name it)."""
    path = write(tmp_path, text)
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    return info.value


def assert_names(error: ScenarioError, key: str, *reason_words: str) -> str:
    """One line of the message is `FILE: KEY: reason` with all `reason_words` in the reason."""
    for line in str(error).splitlines():
        head = f"{error.source}: {key}: "
        if line.startswith(head) and all(w in line[len(head):] for w in reason_words):
            return line
    raise AssertionError(f"no line `{error.source}: {key}: ...{reason_words}` in:\n{error}")


# --- valid input -------------------------------------------------------------------------------
def test_full_scenario_parses_into_typed_values(tmp_path):
    path = write(tmp_path, FULL)
    s = load_scenario(path)
    assert s.name == "leutner-full" and s.description == "every key set"
    assert s.seeds == (3, 1, 4)
    assert (s.backend.arch, s.backend.precision) == ("gpu", "f32")
    assert s.solver.time_step == 1e-4 and s.solver.theta == 0.75 and s.solver.tolerance == 1e-5
    assert s.solver.max_sweeps == 500 and isinstance(s.solver.max_sweeps, int)
    assert (s.solver.check_every, s.solver.schedule) == (5, "coloured")
    assert (s.solver.alert_ratio, s.solver.gravity) == (0.2, 9.8)
    assert s.material.density == 2500.0 and isinstance(s.material.density, float)
    assert (s.material.friction, s.material.wall_friction) == (0.6, 0.1)
    assert s.bond.mode == "burgers" and s.bond.poisson_ratio == 0.25
    assert s.bond.yield_stress == pytest.approx(1.5e6)
    assert s.bond.gap_tolerance == pytest.approx(2e-5)
    out = s.output
    assert (out.snapshot_every, out.checkpoint_every_s, out.series_every) == (0.1, 30.0, 2)
    prep, shear = s.stages
    assert isinstance(prep, PrepareStage) and isinstance(shear, ShearStage)
    assert prep.courses == ("binder", "surface", "surface")
    assert prep.cylinder_diameter == pytest.approx(0.1)
    assert prep.particles_per_layer == 500 and prep.layer_particle_count("binder") == 500
    assert prep.sample_height_mm == 110.0 and prep.vibration_frequency == 25.0
    assert shear.bond_mode == "paper" and shear.gap == pytest.approx(2e-3)
    assert shear.velocity == pytest.approx(1e-3)                  # 60 mm/min = 1 mm/s
    assert shear.duration == pytest.approx(2.0)
    assert s.text == FULL and s.source == str(path)


def test_defaults_fill_everything_not_given():
    s = parse_scenario(MINIMAL)
    assert s.source == "<string>" and s.description == "" and s.seeds == (1,)
    assert s.backend == BackendConfig(arch="cpu", precision="f64")
    assert s.solver.time_step == 2e-4 and s.solver.max_sweeps == 1000 and s.solver.gravity == 9.81
    assert s.material.density == 2600.0 and s.material.friction == 0.7
    assert s.bond.mode == "paper" and s.bond.yield_stress_MPa == 2.7
    assert s.output.snapshot_every == 0.05
    prep, shear = s.stages
    assert prep.courses == ("binder", "surface") and prep.cylinder_diameter_mm == 150.0
    assert prep.packing_fraction == 0.587 and prep.sample_height_mm == 120.0
    assert shear.displacement_mm == 2.5 and shear.velocity_mm_per_min == 50.0
    assert shear.bond_mode is None and shear.sample == ""
    # from the packing fraction: pi/4 (0.15 m)^2 0.06 m 0.587 / mean binder sphere volume
    assert prep.layer_particle_count("binder") == 1675


def test_particle_count_scales_with_size_scale_cubed():
    base = parse_scenario(MINIMAL).stages[0].layer_particle_count("surface")
    half = parse_scenario(MINIMAL.replace('kind = "prepare"',
                                          'kind = "prepare"\nsize_scale = 0.5')).stages[0]
    assert half.layer_particle_count("surface") == pytest.approx(8 * base, rel=1e-3)


def test_scenario_is_frozen():
    s = parse_scenario(MINIMAL)
    with pytest.raises(pydantic.ValidationError):
        s.name = "other"
    with pytest.raises(pydantic.ValidationError):
        s.solver.time_step = 1.0
    with pytest.raises(pydantic.ValidationError):
        s.stages[0].size_scale = 2.0
    assert isinstance(s.stages, tuple) and isinstance(s.stages[0].courses, tuple)


def test_with_overrides_replaces_only_the_backend():
    s = parse_scenario(MINIMAL)
    gpu = s.with_overrides(arch="gpu")
    assert (gpu.backend.arch, gpu.backend.precision) == ("gpu", "f64")
    f32 = s.with_overrides(precision="f32")
    assert (f32.backend.arch, f32.backend.precision) == ("cpu", "f32")
    assert s.backend.arch == "cpu"                      # the original is untouched
    assert gpu.stages == s.stages and gpu.text == s.text and gpu.solver == s.solver
    assert s.with_overrides() is s
    with pytest.raises(ScenarioError, match=r"backend\.arch: must be 'cpu' or 'gpu', got 'tpu'"):
        s.with_overrides(arch="tpu")


def test_to_settings_and_to_law_carry_the_values():
    s = parse_scenario(FULL)
    st = s.solver.to_settings()
    assert (st.time_step, st.theta, st.tolerance, st.max_sweeps, st.check_every) == \
        (1e-4, 0.75, 1e-5, 500, 5)
    assert (st.schedule, st.alert_ratio, st.colouring) == ("coloured", 0.2, "rounds")
    assert st.sweep_order == "forward"
    assert st.warm_start_extrapolation == 0.5
    assert st.convergence == "quad"
    assert parse_scenario(MINIMAL).solver.to_settings().convergence == "impulse"
    assert parse_scenario(MINIMAL).solver.to_settings().warm_start_extrapolation == 0.0
    assert parse_scenario(MINIMAL).solver.to_settings().sweep_order == "symmetric"
    assert tuple(st.gravity) == (0.0, 0.0, -9.8)
    law = s.bond.to_law()
    assert law.mode == "burgers"
    assert (law.maxwell_stiffness, law.maxwell_viscosity) == (3e6, 4e7)
    assert (law.kelvin_stiffness, law.kelvin_viscosity) == (5e6, 6e7)
    assert law.poisson_ratio == 0.25 and law.friction_after_break == 0.5
    assert law.yield_stress == pytest.approx(1.5e6)     # MPa -> Pa
    assert s.bond.to_law(s.stages[1].bond_mode).mode == "paper"


# --- refusals ----------------------------------------------------------------------------------
def test_unknown_top_level_key(tmp_path):
    err = refusal(tmp_path, "sedes = [1]\n" + MINIMAL)
    assert_names(err, "sedes", "unknown key", "seeds")


def test_resident_schedule_with_quad_convergence_is_refused_when_read(tmp_path):
    """The simulation refused it only when built, after `tcd run` had written run.json,
    scenario.toml and the sample's folder (session 44's docs audit)."""
    err = refusal(tmp_path, MINIMAL.replace("[[stage]]", '[solver]\nschedule = "resident"\n'
                                            'convergence = "quad"\n\n[[stage]]', 1))
    assert_names(err, "solver.convergence", "not measured by the resident schedule")
    load_scenario(write(tmp_path, MINIMAL.replace(
        "[[stage]]", '[solver]\nschedule = "coloured"\nconvergence = "quad"\n\n[[stage]]', 1),
        name="coloured.toml"))


def test_unknown_key_inside_a_stage(tmp_path):
    err = refusal(tmp_path, MINIMAL + "ring_heigth_mm = 60\n")
    assert_names(err, "stage[2].ring_heigth_mm", "unknown key", "ring_height_mm")


def test_unknown_key_inside_a_section(tmp_path):
    err = refusal(tmp_path, MINIMAL + "[solver]\ntimestep = 1e-4\n")
    assert_names(err, "solver.timestep", "unknown key", "time_step")


def test_loader_fields_are_not_keys(tmp_path):
    err = refusal(tmp_path, 'text = "x"\n' + MINIMAL)
    assert_names(err, "text", "unknown key")


def test_wrong_type_is_not_coerced(tmp_path):
    err = refusal(tmp_path, MINIMAL + '[solver]\ntime_step = "2e-4"\nmax_sweeps = 10.5\n')
    assert_names(err, "solver.time_step", "wrong type", "number", "string")
    assert_names(err, "solver.max_sweeps", "wrong type", "integer", "float")


def test_stage_table_instead_of_array_of_tables(tmp_path):
    err = refusal(tmp_path, 'name = "x"\n[stage]\nkind = "prepare"\n')
    assert_names(err, "stage", "wrong type", "[[stage]]")


def test_missing_name(tmp_path):
    err = refusal(tmp_path, MINIMAL.replace('name = "tiny"\n', ""))
    assert_names(err, "name", "required value missing")


def test_missing_stage_kind(tmp_path):
    err = refusal(tmp_path, MINIMAL + "[[stage]]\ngap_mm = 1.0\n")
    assert_names(err, "stage[3].kind", "required value missing", "prepare", "shear")


def test_missing_stages(tmp_path):
    err = refusal(tmp_path, 'name = "x"\n')
    assert_names(err, "stage", "required value missing")


def test_unknown_stage_kind(tmp_path):
    err = refusal(tmp_path, MINIMAL + '[[stage]]\nkind = "compact"\n')
    assert_names(err, "stage[3].kind", "unknown stage kind", "'compact'")


def test_negative_size(tmp_path):
    err = refusal(tmp_path, MINIMAL.replace('kind = "prepare"',
                                            'kind = "prepare"\ncylinder_diameter_mm = -150'))
    assert_names(err, "stage[1].cylinder_diameter_mm", "greater than 0", "-150")


@pytest.mark.parametrize("value", ["0", "-2e-4", "0.0", "nan", "inf"])
def test_time_step_must_be_positive_and_finite(tmp_path, value):
    err = refusal(tmp_path, MINIMAL + f"[solver]\ntime_step = {value}\n")
    assert_names(err, "solver.time_step", "must be")


@pytest.mark.parametrize("section, key, value, where", [
    ("[solver]", "time_step", "1e300", "solver.time_step"),       # ran to t = 7e300 s
    ("[solver]", "time_step", "1e-300", "solver.time_step"),      # would never end
    ("[solver]", "max_sweeps", "4294967297", "solver.max_sweeps"),  # wrapped to 1 in the kernel
    ("[solver]", "check_every", "4294967297", "solver.check_every"),
    ("[material]", "density", "1e308", "material.density"),
    ("[solver]", "gravity", "1e30", "solver.gravity"),   # ran, diverged, and exited 0 (session 42)
])
def test_values_beyond_sane_physics_or_32_bit_kernels_are_refused(tmp_path, section, key, value,
                                                                   where):
    err = refusal(tmp_path, MINIMAL + f"{section}\n{key} = {value}\n")
    assert_names(err, where)


@pytest.mark.parametrize("key, value", [("particles_per_layer", "1000000000"),
                                        ("size_scale", "1e-6"), ("max_sweeps", "4294967297")])
def test_stage_values_beyond_bounds_are_refused_at_once(tmp_path, key, value):
    """particles_per_layer = 1e9 built every radius (about 20 GB) before any check refused it."""
    err = refusal(tmp_path, MINIMAL.replace('kind = "prepare"', f'kind = "prepare"\n{key} = {value}')
                  if key != "max_sweeps" else
                  MINIMAL.replace('kind = "shear"', f'kind = "shear"\n{key} = {value}'))
    assert_names(err, f"stage[{2 if key == 'max_sweeps' else 1}].{key}", "must be")


def test_particles_larger_than_the_cylinder(tmp_path):
    # 16 mm spheres x 2 = 32 mm in a 30 mm cylinder
    err = refusal(tmp_path, MINIMAL.replace(
        'kind = "prepare"', 'kind = "prepare"\ncylinder_diameter_mm = 30\nsize_scale = 2.0'))
    assert_names(err, "stage[1].cylinder_diameter_mm", "larger than the cylinder", "32 mm")


def test_shear_gap_larger_than_ring_height(tmp_path):
    err = refusal(tmp_path, MINIMAL + "ring_height_mm = 60\ngap_mm = 61\n")
    assert_names(err, "stage[2].gap_mm", "smaller than ring_height_mm")


def test_shear_displacement_not_below_the_mould_diameter(tmp_path):
    # at 150 mm the upper ring of a 150 mm mould no longer overlaps the lower one
    err = refusal(tmp_path, MINIMAL + "displacement_mm = 150\n")
    assert_names(err, "stage[2].displacement_mm", "150 mm diameter", "leave the lower one")
    load_scenario(write(tmp_path, MINIMAL + "displacement_mm = 149\n", "ok.toml"))


def test_shear_shorter_than_one_time_step(tmp_path):
    # 0.2 mm at 10 m/s takes 2e-5 s: no step of 2e-4 s (it used to end in a KeyError)
    err = refusal(tmp_path, MINIMAL + "displacement_mm = 0.2\nvelocity_mm_per_min = 600000\n"
                                      "smoothing_window_mm = 0.1\n")
    assert_names(err, "stage[2].velocity_mm_per_min", "less than one time step")


def test_rings_too_short_for_the_prepared_sample(tmp_path):
    # the default sample is 120 mm high: two rings of 50 mm leave 20 mm unconfined
    err = refusal(tmp_path, MINIMAL + "ring_height_mm = 50\n")
    assert_names(err, "stage[2].ring_height_mm", "two rings of 50 mm", "120 mm sample")


def test_sample_shorter_than_its_layers(tmp_path):
    # two 60 mm courses cannot be confined to 100 mm (< 0.9 x 120 mm)
    err = refusal(tmp_path, MINIMAL.replace(
        'kind = "prepare"', 'kind = "prepare"\nsample_height_mm = 100'))
    assert_names(err, "stage[1].sample_height_mm", "108 mm")


def test_column_too_short_for_the_particles(tmp_path):
    err = refusal(tmp_path, MINIMAL.replace(
        'kind = "prepare"', 'kind = "prepare"\ncolumn_height_mm = 100'))
    assert_names(err, "stage[1].column_height_mm", "does not fit", "binder")


def test_shear_needs_a_prepared_sample(tmp_path):
    err = refusal(tmp_path, 'name = "x"\n[[stage]]\nkind = "shear"\n')
    assert_names(err, "stage[1].sample", "preceding prepare stage")


def test_shear_sample_path_is_resolved_and_must_exist(tmp_path):
    (tmp_path / "prep").mkdir()
    (tmp_path / "prep" / "prepared.h5").write_bytes(b"")
    text = 'name = "x"\n[[stage]]\nkind = "shear"\nsample = "prep/prepared.h5"\n'
    s = load_scenario(write(tmp_path, text))
    assert pathlib.Path(s.stages[0].sample) == (tmp_path / "prep" / "prepared.h5").resolve()
    err = refusal(tmp_path, text.replace("prepared.h5", "missing.h5"))
    assert isinstance(err, FileNotFoundError)
    assert_names(err, "stage[1].sample", "no such sample file")


def test_shear_sample_path_may_name_each_seed(tmp_path):
    (tmp_path / "s1.h5").write_bytes(b"")
    (tmp_path / "s2.h5").write_bytes(b"")
    text = 'name = "x"\nseeds = [1, 2]\n[[stage]]\nkind = "shear"\nsample = "s{seed}.h5"\n'
    s = load_scenario(write(tmp_path, text))
    assert s.stages[0].sample.format(seed=2) == str((tmp_path / "s2.h5").resolve())
    err = refusal(tmp_path, text.replace("[1, 2]", "[1, 2, 3]"))
    assert_names(err, "stage[1].sample", "no such sample file", "s3.h5")
    assert "s1.h5" not in str(err)
    err = refusal(tmp_path, text.replace("{seed}", "{sed}"))
    assert_names(err, "stage[1].sample", "only {seed} is known")


def test_shear_stage_may_tighten_the_solver(tmp_path):
    (tmp_path / "s.h5").write_bytes(b"")
    text = 'name = "x"\n[[stage]]\nkind = "shear"\nsample = "s.h5"\ntolerance = 1e-6\nmax_sweeps = 9000\n'
    st = load_scenario(write(tmp_path, text)).stages[0]
    assert st.tolerance == 1e-6 and st.max_sweeps == 9000
    err = refusal(tmp_path, text.replace("1e-6", "-1e-6"))
    assert_names(err, "stage[1].tolerance", "greater than 0")


def test_duplicate_seeds_and_bad_seed(tmp_path):
    err = refusal(tmp_path, "seeds = [1, 2, 1, -3]\n" + MINIMAL)
    assert_names(err, "seeds[4]", "greater than or equal to 0", "-3")
    err = refusal(tmp_path, "seeds = [1, 2, 1]\n" + MINIMAL)
    assert_names(err, "seeds[3]", "duplicate seed 1")


def test_bad_name(tmp_path):
    err = refusal(tmp_path, MINIMAL.replace('"tiny"', '"my run/1"'))
    assert_names(err, "name", "letters, digits")


def test_all_problems_are_listed_one_per_line(tmp_path):
    err = refusal(tmp_path,
                  MINIMAL + 'foo = 1\n[solver]\ntime_step = -1\n[backend]\narch = "tpu"\n')
    lines = str(err).splitlines()
    assert len(lines) == 3 and len(err.problems) == 3
    assert all(line.startswith(f"{tmp_path / 'scenario.toml'}: ") for line in lines)
    assert {k for k, _ in err.problems} == {"stage[2].foo", "solver.time_step", "backend.arch"}


def test_malformed_toml_reports_line_and_column(tmp_path):
    err = refusal(tmp_path, 'name = "x"\n\n[solver]\ntime_step = \n')
    assert_names(err, "line 4, column 13", "malformed TOML")


def test_missing_file(tmp_path):
    path = tmp_path / "nope.toml"
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert isinstance(info.value, FileNotFoundError)
    assert str(path) in str(info.value) and "no such scenario file" in str(info.value)


def test_refusal_happens_at_parse_time_without_simulation():
    with pytest.raises(ValueError):          # ScenarioError is a ValueError
        parse_scenario(MINIMAL + "[solver]\ntime_step = 0\n")


# --- files in the repository -------------------------------------------------------------------
SCENARIO_FILES = sorted((ROOT / "scenarios").glob("*.toml"))


@pytest.mark.skipif(not SCENARIO_FILES, reason="no scenarios/*.toml yet")
@pytest.mark.parametrize("path", SCENARIO_FILES, ids=lambda p: p.name)
def test_repository_scenarios_parse(path):
    s = load_scenario(path)
    assert s.name and s.stages


def test_examples_in_the_documentation_parse():
    doc = ROOT / "docs" / "scenarios.md"
    blocks = re.findall(r"```toml\n(.*?)```", doc.read_text(), flags=re.S)
    assert blocks, "docs/scenarios.md has no ```toml example"
    for block in blocks:
        try:
            s = parse_scenario(block, str(doc))
        except ScenarioError as err:   # an example may shear a sample another run makes
            assert all(k.endswith(".sample") and "no such sample file" in r
                       for k, r in err.problems), str(err)
            continue
        assert s.name and s.stages


@pytest.mark.parametrize("stages, key, words", [
    # a second shear re-bonded and sheared the sheared sample, overwriting the first series
    (["prepare", "shear", "shear"], "stage[3].kind", ("second shear stage",)),
    (["prepare", "prepare", "shear"], "stage[2].kind", ("second prepare stage",)),
    # a prepare after a shear poured new spheres onto the sheared sample
    (["shear+sample", "prepare"], "stage[2].kind", ("prepare stage after the shear",)),
    # the sample file was ignored: the shear took the prepare stage's sample
    (["prepare", "shear+sample"], "stage[2].sample", ("would be ignored",)),
])
def test_stage_sequences_that_would_mix_or_ignore_samples_are_refused(tmp_path, stages, key, words):
    (tmp_path / "s.h5").write_bytes(b"")
    text = 'name = "x"\n' + "".join(
        '[[stage]]\nkind = "shear"\nsample = "s.h5"\n' if kind == "shear+sample"
        else f'[[stage]]\nkind = "{kind}"\n' for kind in stages)
    assert_names(refusal(tmp_path, text), key, *words)


def test_a_derived_sphere_count_has_the_same_bound_as_a_given_one(tmp_path):
    """size_scale = 0.001 with particles_per_layer = 0 asked for 12.2 TiB of radii."""
    err = refusal(tmp_path, MINIMAL.replace('kind = "prepare"', 'kind = "prepare"\nsize_scale = 0.001'))
    assert_names(err, "stage[1].size_scale", "spheres in a binder layer", "at most 1e+07")


def test_unknown_colouring_is_refused():
    text = FULL.replace('colouring = "rounds"', 'colouring = "random"')
    with pytest.raises(ScenarioError, match="colouring"):
        parse_scenario(text)


def test_unknown_sweep_order_is_refused(tmp_path):
    err = refusal(tmp_path, FULL.replace('sweep_order = "forward"', 'sweep_order = "backward"'))
    assert_names(err, "solver.sweep_order", "'forward'", "'symmetric'")
    with pytest.raises(ValueError, match="sweep_order must be one of .*'backward'"):
        SolverSettings(sweep_order="backward")


def test_unknown_convergence_measure_is_refused(tmp_path):
    err = refusal(tmp_path, FULL.replace('convergence = "quad"', 'convergence = "lmgc90"'))
    assert_names(err, "solver.convergence", "'impulse'", "'quad'")
    with pytest.raises(ValueError, match="convergence must be one of .*'lmgc90'"):
        SolverSettings(convergence="lmgc90")


@pytest.mark.parametrize("value", ["1.5", "-0.1"])
def test_warm_start_extrapolation_outside_0_1_is_refused(tmp_path, value):
    err = refusal(tmp_path, FULL.replace("warm_start_extrapolation = 0.5",
                                         f"warm_start_extrapolation = {value}"))
    assert_names(err, "solver.warm_start_extrapolation")
    with pytest.raises(ValueError, match="warm_start_extrapolation"):
        SolverSettings(warm_start_extrapolation=float(value))


def test_a_jitter_too_wide_for_the_column_is_named(tmp_path):
    # 30 mm of jitter each side makes the lattice spacing 76 mm: one site would not fit the
    # 150 mm column; without the jitter it fits, so the jitter is the key to blame
    err = refusal(tmp_path, MINIMAL.replace(
        'kind = "prepare"', 'kind = "prepare"\nlattice_jitter_mm = 40'))
    assert_names(err, "stage[1].lattice_jitter_mm", "does not fit")


def test_settle_speed_must_mean_negligible_motion(tmp_path):
    err = refusal(tmp_path, MINIMAL.replace(
        'kind = "prepare"', 'kind = "prepare"\nsettle_speed = 1e9'))
    assert_names(err, "stage[1].settle_speed")


def test_settings_that_would_fail_only_after_the_run_started_are_refused(tmp_path):
    """projection_passes of 3e9 passed the check and failed in the solver after runs/ was
    made; a density of 1e-300 gave NaN walls; a shear's max_sweeps below check_every."""
    def scenario(table, shear=""):
        return 'name = "tiny"\n' + table + MINIMAL.replace('name = "tiny"\n', "") + shear
    err = refusal(tmp_path, scenario("[solver]\nprojection_passes = 3000000000\n"))
    assert_names(err, "solver.projection_passes", "1000000")
    assert len(str(err).splitlines()) == 1
    err = refusal(tmp_path, scenario("[material]\ndensity = 1e-300\n"))
    assert_names(err, "material.density", "1")
    assert len(str(err).splitlines()) == 1
    err = refusal(tmp_path, scenario("[solver]\ncheck_every = 10\n", "max_sweeps = 5\n"))
    assert_names(err, "stage[2].max_sweeps", "check_every (10)")
    assert load_scenario(write(tmp_path, scenario("[solver]\ncheck_every = 5\n",
                                                  "max_sweeps = 5\n"))).stages[1].max_sweeps == 5


def test_a_byte_order_mark_is_not_an_error(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes("\ufeff".encode() + MINIMAL.encode())
    assert load_scenario(path).name == "tiny"


def test_the_scenario_bound_on_max_sweeps_is_the_engine_s():
    """A scenario's max_sweeps (solver and stage) is bounded as SolverSettings bounds it, so a
    scenario the check accepts never fails when its simulation is built."""
    from tcd import config
    from tcd.state import MAX_SWEEPS
    for model in (config.SolverConfig, config.ShearStage):
        field = model.model_fields["max_sweeps"]
        assert [m.le for m in field.metadata if hasattr(m, "le")] == [MAX_SWEEPS], model


def test_gpu_study_is_the_study_on_the_resident_schedule():
    """scenarios/leutner_shear_gpu.toml is leutner_shear.toml but for its name, description,
    schedule and warm start (the extrapolated one, 0.5: about a fifth fewer sweeps, the
    starting point only): a change to the study's calibrated settings must reach both files."""
    study, gpu = _study_and("leutner_shear_gpu.toml", ("schedule", "warm_start_extrapolation"))
    assert gpu["schedule"] == "resident" != study["schedule"]
    assert (gpu["warm_start_extrapolation"], study["warm_start_extrapolation"]) == (0.5, 0.0)


def _study_and(name: str, solver_keys: tuple) -> tuple[dict, dict]:
    """scenarios/leutner_shear.toml's and scenarios/<name>'s `solver_keys`, once the two
    scenarios are found equal but for those, their names and descriptions."""
    study = load_scenario(ROOT / "scenarios" / "leutner_shear.toml").model_dump()
    other = load_scenario(ROOT / "scenarios" / name).model_dump()
    kept = ({k: study["solver"].pop(k) for k in solver_keys},
            {k: other["solver"].pop(k) for k in solver_keys})
    for d in (study, other):
        for key in ("name", "description", "source", "text"):
            d.pop(key)
    assert other == study
    return kept


# --- session 43's mutation audit of the files and checks that guard the results -------------
# config.py ShearStage._check: a smoothing window as long as the whole shear is refused
def test_a_smoothing_window_as_long_as_the_shear_is_refused():
    from tcd.config import ScenarioError, parse_scenario
    text = (ROOT / "scenarios" / "tiny.toml").read_text()
    assert text.count("smoothing_window_mm = 0.02") == 1
    with pytest.raises(ScenarioError, match=r"stage\[2\]\.smoothing_window_mm: 0\.4 mm must be "
                                            r"smaller than displacement_mm \(0\.4 mm\)"):
        parse_scenario(text.replace("smoothing_window_mm = 0.02", "smoothing_window_mm = 0.4"),
                       "tiny.toml")


def test_a_layer_too_large_for_a_float_is_refused_not_an_overflow(tmp_path):
    """cylinder_diameter_mm = 1e300 with particles_per_layer = 0: the layer's volume overflowed
    a float and the OverflowError escaped as a traceback (session 47's fuzzing)."""
    for extra in ("cylinder_diameter_mm = 1e300",
                  "cylinder_diameter_mm = 1e155\nlayer_height_mm = 1e155\nsample_height_mm = 1e156"):
        err = refusal(tmp_path, MINIMAL.replace('kind = "prepare"', f'kind = "prepare"\n{extra}'))
        assert_names(err, "stage[1].size_scale", "spheres in a binder layer", "at most 1e+07")


@pytest.mark.parametrize("key, value, words", [
    # accepted, then a shear of 2.4e301 s and a vibration of 1e300 s that ran for ever
    ("velocity_mm_per_min", "1e-300", ("mm/min takes 2.4e+301 s, more than 2.1e+09 time steps",)),
    ("vibration_duration", "1e300", ("1e+300 s, more than 2.1e+09 time steps",)),
    ("max_hold_time", "1e300", ("1e+300 s, more than 2.1e+09 time steps",)),
    # accepted, then "particle positions must be finite" deep in the pour
    ("vibration_frequency", "1e300", ("above the 1000 Hz", "time steps of 0.0005 s")),
])
def test_stages_longer_than_a_step_count_or_faster_than_the_steps_are_refused(tmp_path, key,
                                                                               value, words):
    """Session 47's fuzzing of scenarios/tiny.toml (time_step 5e-4)."""
    text, n = re.subn(rf"(?m)^{key} = .*$", f"{key} = {value}",
                      (ROOT / "scenarios" / "tiny.toml").read_text())
    assert n == 1
    stage = "stage[2]" if key == "velocity_mm_per_min" else "stage[1]"
    assert_names(refusal(tmp_path, text), f"{stage}.{key}", *words)


# --- accepted, but doubted: values likely in another unit ----------------------------------------
def test_shipped_scenarios_raise_no_doubt():
    for path in sorted((ROOT / "scenarios").glob("*.toml")):
        assert load_scenario(path).doubts() == [], path.name


@pytest.mark.parametrize("section, key, value, words", [
    ("material", "density", 2.6, ("2.6 kg/m^3", "g/cm^3", "2600 kg/m^3")),
    ("material", "density", 26000.0, ("26000 kg/m^3", "outside 300-20000")),
    ("solver", "gravity", 9810.0, ("1000 times", "mm/s^2", "9.81 m/s^2")),
    ("material", "friction", 35.0, ("angle in degrees", "tan(35 deg) = 0.7")),
    ("material", "wall_friction", 3.0, ("Coulomb coefficient of 3",)),
    ("bond", "friction_after_break", 40.0, ("tan(40 deg) = 0.839",)),
    ("bond", "yield_stress_MPa", 2.7e6, ("2.7e+06 MPa", "Pa?", "is 2.7 MPa")),
    ("bond", "yield_stress_MPa", 2700.0, ("kPa? 2700 kPa is 2.7 MPa",)),
])
def test_a_value_in_another_unit_is_doubted_and_kept(section, key, value, words):
    s = parse_scenario(MINIMAL + f"[{section}]\n{key} = {value!r}\n")
    (doubt,) = s.doubts()
    assert doubt[0] == f"{section}.{key}" and all(w in doubt[1] for w in words), doubt
    assert getattr(getattr(s, section), key) == value          # run as written


def test_a_hint_at_another_unit_only_where_that_unit_gives_a_plausible_value():
    """Expanded polystyrene beads (25 kg/m^3) are no grams per cm^3; a 50 g centrifuge is no
    mm/s^2 (session 49's review)."""
    (doubt,) = parse_scenario(MINIMAL + "[material]\ndensity = 25.0\n").doubts()
    assert "25 kg/m^3 is outside" in doubt[1] and "g/cm^3" not in doubt[1]
    (doubt,) = parse_scenario(MINIMAL + "[solver]\ngravity = 490.5\n").doubts()
    assert "50 times" in doubt[1] and "mm/s^2" not in doubt[1] and "centrifuge" in doubt[1]


def test_the_bounds_of_doubt():
    edge = "[material]\ndensity = 300.0\nfriction = 2.0\n[solver]\ngravity = 98.1\n"
    assert parse_scenario(MINIMAL + edge).doubts() == []
    s = parse_scenario(MINIMAL.replace('kind = "shear"', 'kind = "shear"\nwall_friction = 2.5'))
    assert [k for k, _ in s.doubts()] == ["stage[2].wall_friction"]


def test_the_tolerance_study_is_the_study_at_a_tenth_of_its_tolerance():
    """scenarios/leutner_shear_tol1e-6.toml is leutner_shear.toml but for its name,
    description, tolerance (1e-6 against 1e-5) and sweep cap: a change to the study's
    calibrated settings must reach both files."""
    study, tight = _study_and("leutner_shear_tol1e-6.toml", ("tolerance", "max_sweeps"))
    assert (tight["tolerance"], study["tolerance"]) == (1e-6, 1e-5)
    assert (tight["max_sweeps"], study["max_sweeps"]) == (200000, 5000)


def test_the_calibrated_study_at_1e_6_is_the_tolerance_study_with_its_own_yield_stress():
    """scenarios/leutner_shear_calibrated_1e-6.toml is leutner_shear_tol1e-6.toml but for its
    name, description and yield stress (1.63 MPa, session 59's scan at 1e-6, against 1.7): a
    change to the study's other settings must reach it too."""
    tight = load_scenario(ROOT / "scenarios" / "leutner_shear_tol1e-6.toml").model_dump()
    calibrated = load_scenario(ROOT / "scenarios" / "leutner_shear_calibrated_1e-6.toml").model_dump()
    assert (calibrated["bond"].pop("yield_stress_MPa"), tight["bond"].pop("yield_stress_MPa")) == (1.63, 1.7)
    for d in (tight, calibrated):
        for key in ("name", "description", "source", "text"):
            d.pop(key)
    assert calibrated == tight
