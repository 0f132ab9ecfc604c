"""What one time step asks of the host: kernel launches and host reads of Taichi fields per step.

    python benchmarks/step_inventory.py shear --sample samples/leutner_seed1_prepared.h5 --time 0.01 --schedule resident
    TCD_AUTO=gpu python benchmarks/step_inventory.py shear --sample ... --schedule resident   # the GPU's path on this CPU
    python benchmarks/step_inventory.py pour --particles 2600 --time 0.1

Runs `tcd bench pour` or `tcd bench shear` and counts, over every step but the first two (which
compile), each kernel launch by kernel and each read of a field from Python (`field[i]`,
`to_numpy`, or a kernel's return value) and write (`field[i] = `, `from_numpy`) by the line of tcd/ that made it. On a GPU a
launch costs the host tens of microseconds and a read waits for the device to finish what was
queued, so these counts bound the step's host-side cost whatever the kernels' own time
(benchmarks/profile.py gives that). The counts do not depend on the machine: the same Python
runs on every backend (with TCD_AUTO=gpu the CPU takes the GPU's choices of schedule and
colouring).
"""
import argparse
import collections
import json
import os
import sys
import traceback

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from taichi.lang import kernel_impl  # noqa: E402
from taichi.lang.field import ScalarField  # noqa: E402
from taichi.lang.matrix import MatrixField  # noqa: E402

from tcd import bench, simulation  # noqa: E402

PACKAGE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tcd")


class Inventory:
    """Counts launches, reads and writes while `active` (set for each counted step)."""

    def __init__(self):
        self.launches = collections.Counter()
        self.reads = collections.Counter()
        self.writes = collections.Counter()
        self.active = False
        self.steps = 0

    @staticmethod
    def site() -> str:
        """The innermost line of tcd/ on the stack (the call that reached Taichi)."""
        package = os.path.realpath(PACKAGE)
        for frame in reversed(traceback.extract_stack()[:-2]):
            if os.path.realpath(frame.filename).startswith(package):
                return f"{os.path.basename(frame.filename)}:{frame.lineno}"
        return "elsewhere"

    def install(self, skip: int):
        """Patch Taichi's kernel calls and field accessors and Simulation._step to count;
        uninstall() puts them back."""
        inv = self
        self._saved = []
        depth = [0]         # a field access inside another (a vector's components) is not counted

        def patch(cls, name, make):
            self._saved.append((cls, name, cls.__dict__.get(name)))
            setattr(cls, name, make(getattr(cls, name)))

        def kernel_call(call):
            def counted_call(kernel, *args, **kwargs):
                counted = inv.active and depth[0] == 0
                if counted:
                    inv.launches[kernel.func.__name__] += 1
                result = call(kernel, *args, **kwargs)
                if counted and result is not None:
                    # a kernel's return value is a read: the host waits for the device
                    inv.reads["returned by " + kernel.func.__name__] += 1
                return result
            return counted_call
        patch(kernel_impl.Kernel, "__call__", kernel_call)

        def access(counter, label):
            def make(original):
                def counted(field, *args, **kwargs):
                    if inv.active and depth[0] == 0:
                        counter[label + inv.site()] += 1
                    depth[0] += 1
                    try:
                        return original(field, *args, **kwargs)
                    finally:
                        depth[0] -= 1
                return counted
            return make
        for cls in (ScalarField, MatrixField):
            patch(cls, "__getitem__", access(self.reads, ""))
            patch(cls, "__setitem__", access(self.writes, ""))
            patch(cls, "to_numpy", access(self.reads, "to_numpy at "))
            patch(cls, "from_numpy", access(self.writes, "from_numpy at "))
        seen = [0]

        def stepper(step):
            def counted_step(sim):
                seen[0] += 1
                inv.active = seen[0] > skip
                inv.steps += int(inv.active)
                try:
                    return step(sim)
                finally:
                    inv.active = False
            return counted_step
        patch(simulation.Simulation, "_step", stepper)

    def uninstall(self):
        for cls, name, original in reversed(self._saved):
            if original is None:
                delattr(cls, name)
            else:
                setattr(cls, name, original)
        self._saved = []

    def table(self) -> dict:
        n = max(self.steps, 1)

        def per_step(counter):
            return {k: round(v / n, 3) for k, v in counter.most_common()}
        return {"steps_counted": self.steps,
                "launches_per_step": round(sum(self.launches.values()) / n, 3),
                "reads_per_step": round(sum(self.reads.values()) / n, 3),
                "writes_per_step": round(sum(self.writes.values()) / n, 3),
                "launches": per_step(self.launches), "reads": per_step(self.reads),
                "writes": per_step(self.writes)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("benchmark", choices=("pour", "shear"))
    ap.add_argument("--particles", type=int, default=None)
    ap.add_argument("--time", type=float, default=0.01)
    ap.add_argument("--arch", default="cpu", choices=("cpu", "gpu"))
    ap.add_argument("--precision", default="f64", choices=("f64", "f32"))
    ap.add_argument("--sample", default=None)
    ap.add_argument("--samples", type=int, default=1)
    ap.add_argument("--schedule", default="auto")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    a = ap.parse_args(argv)
    inv = Inventory()
    inv.install(skip=bench.WARMUP_STEPS)
    try:
        if a.benchmark == "pour":
            out = bench.pour(a.particles or 2600, a.time, a.arch, a.precision, schedule=a.schedule)
        else:
            out = bench.shear(a.particles or 5200, a.time, a.arch, a.precision, sample=a.sample,
                              samples=a.samples, schedule=a.schedule)
    finally:
        inv.uninstall()
    table = inv.table()
    table.update({k: out[k] for k in ("particles", "steps", "mean_sweeps", "arch", "precision")},
                 schedule=a.schedule, auto=os.environ.get("TCD_AUTO", ""))
    if a.json:
        print(json.dumps(table))
        return table
    print(f"{table['steps_counted']} steps counted ({out['particles']} particles, "
          f"{out['mean_sweeps']:.2f} mean sweeps)")
    for name in ("launches", "reads", "writes"):
        print(f"{name} per step: {table[name + '_per_step']}")
        for k, v in table[name].items():
            print(f"  {k:50s} {v:8.3f}")
    return table


if __name__ == "__main__":
    main()
