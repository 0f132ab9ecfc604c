"""Pour grains into a cylinder, let them settle, weigh them on the floor, save the snapshots.

Spheres of the paper's binder course (PHYSICS.md section 7), scaled down, are placed at random
sites of a cubic lattice in a column and poured by gravity into a frictionless cylinder
(grain friction 0.7). At rest, the mould's walls carry no vertical load, so the floor must carry
the whole weight, M g. The script steps until the grains' mass-weighted rms speed falls below
`--settle-speed` (tcd.protocols.settled, the rule of the sample preparation: translation only,
since a grain spinning about the vertical on a point contact meets no drilling friction),
prints the floor's force over the last 0.05 s against M g, the packing fraction and the largest overlap, and
writes the snapshots to a states file that `tcd info`, `tcd render` and `tcd export` read.

    python examples/pour.py [--particles 300] [--scale 0.5] [--seed 1] [--out pour_states.h5]
        [--arch cpu|gpu]
    tcd render pour_states.h5 --out pour.png
"""
from __future__ import annotations

import argparse
import collections
import math

import numpy as np

G = 9.81


def run(particles: int = 300, scale: float = 0.5, seed: int = 1, out: str | None = None,
        settle_speed: float = 1e-3, max_time: float = 2.0, h: float = 2e-4,
        snapshot_every: float = 0.1) -> dict:
    """Pour `particles` binder-course spheres (diameters 2-16 mm times `scale`) into a mould
    80 mm times `scale` wide until they settle or `max_time` s pass; the numbers of the bed.
    Snapshots go to `out` (a tcd states file) if given. tcd.init must have been called."""
    from tcd import io, observables, packing, walls
    from tcd.protocols import settled as at_rest
    from tcd.runner import frame_of
    from tcd.simulation import Simulation, SolverSettings

    rng = np.random.default_rng(seed)
    radii = packing.course_radii("binder", particles, rng) * scale
    mould = 0.08 * scale                                       # inner diameter (m)
    x = packing.lattice_column(radii, mould, 0.0, rng, jitter=2e-4 * scale)
    top = float(x[:, 2].max() + radii.max())
    mould_walls = [walls.plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), name="floor"),
                   walls.cylinder((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), mould / 2, (0.0, top),
                                  name="mould")]             # frictionless, as in the paper
    sim = Simulation(radii, x, walls=mould_walls, friction=0.7,
                     settings=SolverSettings(time_step=h),
                     domain=((-mould / 2,) * 2 + (0.0,), (mould / 2,) * 2 + (top,)))
    mass = float(np.sum(sim.density * 4.0 / 3.0 * math.pi * radii**3))
    every = max(1, int(round(snapshot_every / h)))
    window = int(round(0.05 / h))                            # the floor force's average
    steps, settled, sweeps, floor = 0, False, [], collections.deque(maxlen=window)
    while steps * h < max_time:
        rec = sim.step()
        steps += 1
        sweeps.append(rec.sweeps)
        floor.append(float(sim.wall_force(0)[2]))
        if out and steps % every == 0:
            io.append_frame(out, frame_of(sim), time=sim.time, step=steps, stage="pour")
        if steps >= window and at_rest(sim, settle_speed):
            settled = True
            break
    if out and steps % every != 0:          # the last state, unless just written
        io.append_frame(out, frame_of(sim), time=sim.time, step=steps, stage="pour")
    pos, r = sim.positions(), sim.radii()
    bed_top = float(np.max(pos[:, 2] + r))
    gaps = sim.contact_arrays()["gap"]
    result = {"settled": settled, "time": steps * h, "steps": steps,
              "mean_sweeps": float(np.mean(sweeps)), "weight": mass * G,
              "floor_force": float(np.mean(floor)),
              "mould_vertical_force": float(sim.wall_force(1)[2]),
              "bed_height": bed_top,
              "packing_fraction": observables.packing_fraction(pos, r, mould / 2, 0.0, bed_top),
              "outside": observables.outside(pos, r, mould / 2, 0.0, top),
              "max_overlap_ratio": float(max(0.0, -gaps.min(initial=0.0)) / (2 * r.min()))}
    sim.close()
    return result


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--scale", type=float, default=0.5,
                    help="grain sizes relative to the paper's (1: 2-16 mm, in an 80 mm mould)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--settle-speed", type=float, default=1e-3,
                    help="settled when the mass-weighted rms speed is below this (m/s)")
    ap.add_argument("--out", default=None, help="states file (HDF5) for the snapshots")
    ap.add_argument("--arch", choices=("cpu", "gpu"), default="cpu")
    a = ap.parse_args()
    import tcd
    tcd.init(a.arch, "f64")
    o = run(a.particles, a.scale, a.seed, a.out, a.settle_speed)
    print(f"{a.particles} grains {'settled' if o['settled'] else 'NOT settled'} after "
          f"{o['time']:.3f} s ({o['steps']} steps, {o['mean_sweeps']:.1f} mean sweeps per step)")
    print(f"floor force (mean of the last 0.05 s) {-o['floor_force']:.5f} N against the weight {o['weight']:.5f} N "
          f"(ratio {-o['floor_force'] / o['weight']:.4f}); the mould's vertical force "
          f"{o['mould_vertical_force']:.1e} N")
    print(f"bed {o['bed_height'] * 1e3:.1f} mm high, packing fraction "
          f"{o['packing_fraction']:.3f}, largest overlap {o['max_overlap_ratio']:.2%} of the "
          f"smallest diameter, {o['outside']} grains outside")
    if a.out:
        print(f"snapshots in {a.out}: tcd info {a.out}; tcd render {a.out} --out pour.png")


if __name__ == "__main__":
    main()
