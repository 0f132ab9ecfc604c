"""benchmarks/step_inventory.py counts what a step asks of the host: kernel launches by kernel,
field reads and writes by the line of tcd/ that made them, over the steps after the two that
compile; and it leaves Taichi and Simulation as it found them."""
from taichi.lang import kernel_impl
from taichi.lang.field import ScalarField
from taichi.lang.matrix import MatrixField

from tcd import simulation


def test_inventory_counts_one_solver_launch_per_step_and_restores_taichi(benchmark_script, capsys,
                                                                        backend):
    inventory = benchmark_script("step_inventory")
    before = [kernel_impl.Kernel.__call__, simulation.Simulation._step,
              ScalarField.__dict__["__getitem__"], MatrixField.__dict__["to_numpy"]]
    arch, precision = backend
    table = inventory.main(["pour", "--particles", "300", "--time", "0.002", "--schedule",
                            "serial", "--arch", arch, "--precision", precision, "--json"])
    assert table["steps"] == 10 and table["steps_counted"] == 8
    # the serial schedule: all sweeps of a step in one launch, and one launch each before and
    # after them (solver.step_begin: the contacts' filling to the warm start; step_end: the
    # bonds' update to the contacts' history), none of the kernels they hold launched alone;
    # with the neighbour list's check and the contacts' count with its scan (one launch since
    # session 68), five launches a step
    for kernel in ("nlgs_serial", "step_begin", "step_end"):
        assert table["launches"][kernel] == 1.0, kernel
    for kernel in ("predict", "apply_warm_start", "integrate", "wall_forces", "save_history",
                   "contact_pass", "_exclusive_scan"):
        assert kernel not in table["launches"], kernel
    assert table["launches"]["_contact_count_scan"] == 1.0   # the count; step_begin fills
    assert table["launches_per_step"] == sum(table["launches"].values()) == 5.0
    # every read is attributed to a line of tcd/ (the step's totals and records) or to a
    # launched kernel's return value (the host waits for it)
    assert table["reads_per_step"] >= 3
    for key in table["reads"]:
        if key.startswith("returned by "):
            assert key[len("returned by "):] in table["launches"], key
        else:
            assert key.split(" at ")[-1].split(":")[0].endswith(".py"), key
    # the serial pour's contact count is returned by the count's scan, once per step at least
    assert table["reads"]["returned by _contact_count_scan"] >= 1.0
    assert '"launches_per_step"' in capsys.readouterr().out
    after = [kernel_impl.Kernel.__call__, simulation.Simulation._step,
             ScalarField.__dict__["__getitem__"], MatrixField.__dict__["to_numpy"]]
    assert after == before
