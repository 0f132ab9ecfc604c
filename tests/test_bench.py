"""The benchmarks' own bookkeeping (their speed is measured by `tcd bench`, never here)."""
import csv
import math
import types

import numpy as np
import pytest

from tcd import bench


def test_scaling_scan_keeps_finished_sizes_when_interrupted(tmp_path, monkeypatch, on_backend):
    """The scan writes its CSV and plot after every size: a scan stopped during its second size
    keeps the first size's row, with the residual and sweeps that its timing bought."""
    real_setup = bench.pour_setup
    seen = []

    def setup(particles, *args, **kwargs):
        if particles == 600:
            raise KeyboardInterrupt
        return real_setup(particles, *args, **kwargs)
    monkeypatch.setattr(bench, "pour_setup", setup)
    out = tmp_path / "scan" / "scaling"
    with pytest.raises(KeyboardInterrupt):
        bench.scaling(sizes=(300, 600), steps=4, out=str(out), progress=seen.append,
                      **on_backend)
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    assert [int(r["particles"]) for r in rows] == [300] and [r["particles"] for r in seen] == [300]
    row = rows[0]
    assert float(row["seconds_per_particle_step"]) > 0 and int(row["timed_steps"]) == 4 - bench.WARMUP_STEPS == 2
    assert float(row["final_residual"]) <= 1e-4 or int(row["max_sweeps_hit"]) > 0
    assert float(row["memory_bytes_per_particle"]) > 0
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # nothing half-written is left beside the outputs
    assert sorted(p.name for p in out.parent.iterdir()) == ["scaling.csv", "scaling.png"]


@pytest.mark.parametrize("options, message", [
    ({"sizes": (100,)}, "at least 300 spheres"),
    ({"steps": 2}, "steps 2: at least 3"),       # divided by the timed steps (steps - 2) at the end
    ({"out": "/proc/no/such/scaling"}, "cannot write into /proc/no/such"),
    ({"settle": -0.1}, "settle -0.1: expected a finite time >= 0"),
    ({"settle": float("nan")}, "settle nan"),
])
def test_scaling_checks_its_arguments_before_the_first_size(tmp_path, monkeypatch, options, message):
    monkeypatch.setattr(bench, "pour_setup", lambda *a, **k: pytest.fail("a size was run"))
    kwargs = {"sizes": (300,), "steps": 3, "out": str(tmp_path / "scaling"), **options}
    with pytest.raises(ValueError, match=message):
        bench.scaling(**kwargs)
    assert list(tmp_path.iterdir()) == []


def test_a_benchmark_without_a_timed_step_is_refused(on_backend):
    """The first two steps compile and are not timed: --time below three steps would time
    nothing (below two it used to run two steps silently)."""
    assert bench.WARMUP_STEPS == 2
    for time in (1e-5, 2 * 2e-4, float("nan")):
        with pytest.raises(ValueError, match="less than 3 time steps"):
            bench.pour(particles=10, time=time, **on_backend)
    for time in (0.0006, 3 * 2e-4, 2.6 * 2e-4):     # three steps, whatever the rounding
        bench._check_steps(time)


def test_a_pour_too_tall_for_the_mould_points_to_the_scaling_benchmark(on_backend):
    """A million spheres do not fit a 150 mm mould under 100 m of lattice column: the refusal
    names the benchmark that widens the cylinder with N (the GPU's 1e6 row)."""
    with pytest.raises(ValueError, match=r"above max_height.*tcd bench scaling --sizes 1000000"):
        bench.pour(particles=1_000_000, time=0.01, **on_backend)


def test_pour_reports_its_phases_and_writes_a_step_trace(tmp_path, on_backend):
    """The phases cut the timed steps into windows that add up to the whole loop (steps,
    wall time, sweeps); the trace has one row per timed step with the same sweeps."""
    trace = tmp_path / "pour.csv"
    out = bench.pour(particles=60, time=0.02, trace=str(trace), **on_backend)
    ph = out["phases"]
    assert len(ph) == 10 and sum(p["steps"] for p in ph) == out["steps"] - 2 == 98
    # the phases' wall time is the timed steps' (the trace's rows; each phase rounded to 1 us),
    # within the loop's own (which adds the Python between two steps: on a loaded machine a
    # wait there is not a step's)
    step_walls = [float(r["wall_s"]) for r in csv.DictReader(open(trace))]
    assert sum(p["wall_s"] for p in ph) == pytest.approx(sum(step_walls), abs=1e-5)
    assert sum(step_walls) <= out["loop_wall_s"] * (1 + 1e-6)
    assert sum(p["wall_share"] for p in ph) == pytest.approx(1.0, abs=1e-3)
    rows = list(csv.DictReader(open(trace)))
    assert out["trace"] == str(trace) and len(rows) == 98
    sweeps = [int(r["sweeps"]) for r in rows]
    assert sum(sweeps) / len(sweeps) == pytest.approx(out["mean_sweeps"])
    assert sum(p["mean_sweeps"] * p["steps"] for p in ph) == pytest.approx(sum(sweeps), rel=1e-3)
    times = [float(r["time_s"]) for r in rows]
    assert times[0] == pytest.approx(3 * 2e-4) and times[-1] == pytest.approx(0.02)
    assert ph[0]["time_s"][0] == pytest.approx(times[0]) and ph[-1]["time_s"][1] == pytest.approx(times[-1])
    assert int(rows[-1]["contacts"]) == out["contacts"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pour.csv"]     # no .part left


def test_a_trace_into_a_missing_folder_is_refused_before_the_run(tmp_path, monkeypatch,
                                                                  on_backend):
    monkeypatch.setattr(bench, "pour_setup", lambda *a, **k: pytest.fail("the pour was run"))
    with pytest.raises(FileNotFoundError, match="no such directory"):
        bench.pour(particles=60, time=0.02, trace=str(tmp_path / "nope" / "pour.csv"),
                   **on_backend)
    with pytest.raises(ValueError, match="is a directory; give a file name"):
        bench.pour(particles=60, time=0.02, trace=str(tmp_path), **on_backend)


def test_a_shear_batch_beyond_the_systems_of_one_simulation_is_refused_at_once(monkeypatch,
                                                                             on_backend):
    """--samples 65 prepared every sample (minutes) before the batch refused it (session 42
    audit); now the count is checked before anything is made."""
    monkeypatch.setattr(bench, "bench_sample", lambda *a, **k: pytest.fail("a sample was made"))
    from tcd.state import MAX_SYSTEMS
    with pytest.raises(ValueError, match=f"samples must be 1 to {MAX_SYSTEMS}"):
        bench.shear(particles=50, time=0.001, samples=MAX_SYSTEMS + 1, **on_backend)


def test_a_trace_into_a_folder_that_cannot_be_written_is_refused_before_the_run(tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("a file")
    with pytest.raises(FileNotFoundError, match="no such directory"):
        bench.check_trace(str(blocker / "t.csv"))
    with pytest.raises(ValueError, match="cannot write into /proc"):
        bench.check_trace("/proc/t.csv")


# --- session 43's mutation audit of the walls, the API, the benchmarks and the renderer -------
class _BedStub:
    """What bench.bed_metrics reads of a Simulation."""

    def __init__(self, x, r, gap):
        self._x, self._r, self._gap = np.asarray(x, float), np.asarray(r, float), np.asarray(gap, float)

    def positions(self):
        return self._x.copy()

    def radii(self):
        return self._r.copy()

    def contact_arrays(self):
        m = len(self._gap)
        return {"i": np.zeros(m, int), "j": np.ones(m, int), "gap": self._gap.copy()}


def test_bed_metrics_are_the_documented_closed_forms():
    """highest top = max(z + r); packing fraction = sphere volume / (pi R^2 top);
    max_overlap_ratio = largest interpenetration / smallest DIAMETER; outside counts centres
    beyond the mould (not grains that only poke through it)."""
    r = np.array([0.01, 0.02, 0.005, 0.005])
    # third: centre outside the mould; fourth: pokes through it, centre inside (not counted)
    x = np.array([[0.0, 0.0, 0.01], [0.03, 0.0, 0.03], [0.0, 0.08, 0.005], [0.072, 0.0, 0.005]])
    sim = _BedStub(x, r, gap=[-0.001, 0.0005, -0.0002])
    m = bench.bed_metrics(sim, radius=0.075)
    assert m["highest_top_m"] == pytest.approx(0.05, rel=1e-12)
    volume = 4.0 / 3.0 * math.pi * np.sum(r**3)
    assert m["packing_fraction"] == pytest.approx(volume / (math.pi * 0.075**2 * 0.05), rel=1e-12)
    assert m["max_overlap_ratio"] == pytest.approx(0.001 / 0.01, rel=1e-12)   # r.min() = 5 mm
    assert m["outside"] == 1 and m["contacts"] == 3
    # no interpenetration: ratio 0, never negative
    assert bench.bed_metrics(_BedStub(x, r, gap=[0.001]))["max_overlap_ratio"] == 0.0


class _ClockSim:
    """A Simulation stand-in whose every step costs one second of a fake clock."""

    def __init__(self, clock):
        self.clock, self.steps = clock, 0

    def step(self):
        self.clock[0] += 1.0
        self.steps += 1
        return types.SimpleNamespace(sweeps=self.steps, residual=0.0, contacts=7,
                                     time=self.steps * 1e-3, colours=0)


def test_the_loop_times_only_the_steps_after_the_compiling_ones(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(bench.time, "perf_counter", lambda: clock[0])
    sim = _ClockSim(clock)
    compile_s, loop_s, sweeps, _, _, per_step = bench._loop(sim, 10)
    assert sim.steps == 10
    assert compile_s == bench.WARMUP_STEPS == 2
    assert loop_s == 10 - bench.WARMUP_STEPS
    assert sweeps.tolist() == list(range(3, 11))           # the timed steps' records only
    assert per_step["wall_s"].tolist() == [1.0] * 8


def test_pour_divides_the_loop_time_by_particles_times_timed_steps(monkeypatch):
    """seconds_per_particle_step = loop time / (particles * timed steps); mean_sweeps the mean
    of the timed steps'; bytes per particle = memory / particles."""
    n, h = 40, 2e-4
    r = np.full(n, 0.005)
    x = np.zeros((n, 3))
    x[:, 2] = 0.005 + 0.01 * np.arange(n)
    sim = _BedStub(x, r, gap=[-1e-4])
    sim.settings = types.SimpleNamespace(time_step=h, max_sweeps=100, check_every=1,
                                         warm_start_extrapolation=0.0, convergence="impulse")
    sim.schedule, sim.sweep_order_used, sim.acceleration_used = "serial", "symmetric", "nncg"
    sim.resident_block = {}
    sim.memory_bytes = lambda: 8000
    steps = 10                                                  # time 2e-3 s
    sweeps = np.array([1, 1, 1, 1, 1, 1, 1, 9], float)          # mean 2, median 1
    per_step = {"wall_s": np.full(8, 0.5), "contacts": np.ones(8, int),
                "time_s": h * np.arange(3, 11)}
    monkeypatch.setattr(bench, "_init", lambda *a: None)
    monkeypatch.setattr(bench, "pour_setup", lambda *a, **k: sim)
    monkeypatch.setattr(bench, "_loop", lambda s, k: (1.0, 4.0, sweeps, np.zeros(8), 0, per_step))
    out = bench.pour(particles=n, time=steps * h)
    assert out["steps"] == steps
    assert out["seconds_per_particle_step"] == pytest.approx(4.0 / (n * 8), rel=1e-12)
    assert out["mean_sweeps"] == pytest.approx(2.0)
    assert out["memory_bytes_per_particle"] == pytest.approx(8000 / n)
    assert out["loop_wall_s"] == 4.0 and out["compile_wall_s"] == 1.0



@pytest.mark.f64_only   # a limit of the time scheme, not of the precision
def test_a_loaded_bond_rolls_stably_below_the_explicit_frame_s_limit(benchmark_script, backend):
    """benchmarks/bond_rolling_stability.py: a grain pulled along its one bond, free to roll
    about its fixed partner, is an explicit pendulum (the bond's frame is the step's start),
    stable below F H^2 / (m L) = 4 x 7/5 = 5.6 (docs/physics.md, "Limitations"): at 5.51 it
    stays on the axis, at 5.69 it leaves it. With bond_frame = "end" it stays on the axis at
    5.69 and at 14.7 (8 N, where the default breaks the bond)."""
    script = benchmark_script("bond_rolling_stability")
    stable, unstable = script.run(3.0, 2e-4, 200), script.run(3.1, 2e-4, 200)
    assert 5.5 < stable["stability_number"] < 5.6 < unstable["stability_number"] < 5.7
    assert stable["off_axis_m"] < 1e-12 and stable["bonds"] == (1, 0, 0)
    assert unstable["off_axis_m"] > 1e-5
    for force in (3.1, 8.0):
        turned = script.run(force, 2e-4, 200, bond_frame="end")
        assert turned["off_axis_m"] < 1e-12 and turned["bonds"] == (1, 0, 0), turned
