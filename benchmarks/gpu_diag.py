"""Smallest GPU check: one sphere resting on a plane for a few steps (device diagnosis).
python benchmarks/gpu_diag.py [gpu|cpu] [f64|f32]: prints the normal impulse per step."""
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import tcd  # noqa: E402
from tcd import walls  # noqa: E402
from tcd.simulation import Simulation, SolverSettings  # noqa: E402

arch = sys.argv[1] if len(sys.argv) > 1 else "gpu"
precision = sys.argv[2] if len(sys.argv) > 2 else "f64"
tcd.init(arch, precision)
if os.environ.get("TCD_SYNC_TRACE"):
    # every kernel of tcd followed by ti.sync() and named first: the last name printed before
    # an asynchronous CUDA error is the kernel that raised it
    import taichi as ti
    from tcd import contacts, partitioned, simulation, solver, state

    def traced(name, k):
        def call(*a, **kw):
            print("KERNEL", name, flush=True)
            out = k(*a, **kw)
            ti.sync()
            return out
        return call
    for mod in (contacts, partitioned, solver, state, simulation):
        for name in dir(mod):
            obj = getattr(mod, name)
            if callable(obj) and hasattr(obj, "_primal"):
                setattr(mod, name, traced(f"{mod.__name__}.{name}", obj))
r = 0.005
sim = Simulation([r], [(0.0, 0.0, r)], walls=[walls.plane((0, 0, 0), (0, 0, 1))],
                 settings=SolverSettings(tolerance=1e-10, max_sweeps=100),
                 domain=((-0.05,) * 3, (0.05,) * 3))
for _ in range(5):
    rec = sim.step()
c = sim.contact_arrays()
mass = 2500.0 * 4.0 / 3.0 * 3.141592653589793 * r**3
print(f"DIAG {arch} {precision} layout={os.environ.get('TCD_LAYOUT', 'default')}: contacts "
      f"{rec.contacts}, sweeps {rec.sweeps}, impulse {c['impulse'][0] if len(c['impulse']) else None}, "
      f"m g H = {mass * 9.81 * sim.settings.time_step:.6e}, z = {sim.positions()[0, 2]:.9f}")
