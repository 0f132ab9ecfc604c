"""Does a frictional pyramid keep its mirror symmetry (docs/physics.md, "Limitations")?

Stacks spheres in a pyramid on a frictional floor, steps it and prints, per step, how far the
positions and spins are from their mirror image in x -> -x. A plane pyramid (4 + 3 + 2 + 1
grains in rows along x) is run twice, numbered left to right and right to left, and the second
run is compared with the mirror image of the first: equal, the numbering picks only the
round-off. A square pyramid (16 + 9 + 4 + 1) is run once.

    python benchmarks/pyramid_symmetry.py [--shape plane|square] [--radius 0.0025]
        [--drop 0] [--spacing 0] [--friction 0.5] [--steps 40] [--tolerance 1e-12]
"""
from __future__ import annotations

import argparse
import math

import numpy as np

SOLVERS = {"default": {}, "plain symmetric": {"acceleration": "none"},
           "plain forward": {"acceleration": "none", "sweep_order": "forward"}}


def pyramid(shape: str, r: float, drop: float, spacing: float) -> np.ndarray:
    """Centres of the pyramid: rows (plane) or layers (square) of 4, 3, 2, 1 grains a side,
    `spacing` apart in a row, each level `drop` above resting on the one below."""
    d = 2 * r + spacing
    rise = math.sqrt((2 * r) ** 2 - (d / 2) ** 2 * (2 if shape == "square" else 1))
    pts = []
    for level in range(4):
        k = 4 - level
        z = r + drop + level * (rise + drop)
        ys = [(b - (k - 1) / 2) * d for b in range(k)] if shape == "square" else [0.0]
        for a in range(k):
            for y in ys:
                pts.append(((a - (k - 1) / 2) * d, y, z))
    return np.array(pts)


def mirror_partner(pts: np.ndarray) -> np.ndarray:
    return np.array([np.argmin(np.linalg.norm(pts - p * (-1, 1, 1), axis=1)) for p in pts])


def run(pts, order, r, mu, steps, tolerance, solver):
    """Positions and spins after each step, in the canonical numbering."""
    from tcd import walls
    from tcd.simulation import Simulation, SolverSettings
    inv = np.argsort(order)
    s = SolverSettings(time_step=2e-4, tolerance=tolerance, max_sweeps=100000, **solver)
    sim = Simulation(np.full(len(pts), r), pts[order], friction=mu, settings=s,
                     walls=[walls.plane((0, 0, 0), (0, 0, 1), friction=mu)],
                     domain=((-0.05, -0.05, -0.01), (0.05, 0.05, 0.08)))
    out = []
    for _ in range(steps):
        sim.step(1)
        out.append((sim.positions()[inv], sim.angular_velocities()[inv]))
    sim.close()
    return out


def asymmetry(x, w, m):
    """Largest distance of positions and spins from their mirror image (a spin, an axial
    vector, mirrors in x as (w_x, -w_y, -w_z))."""
    return np.abs(x[m] * (-1, 1, 1) - x).max(), np.abs(w[m] * (1, -1, -1) - w).max()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shape", choices=("plane", "square"), default="plane")
    ap.add_argument("--radius", type=float, default=0.0025, help="m")
    ap.add_argument("--drop", type=float, default=0.0, help="gap between levels (m)")
    ap.add_argument("--spacing", type=float, default=0.0, help="gap between grains of a row (m)")
    ap.add_argument("--friction", type=float, default=0.5)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--tolerance", type=float, default=1e-12)
    ap.add_argument("--solver", choices=tuple(SOLVERS), action="append",
                    help="repeatable; default: all three")
    a = ap.parse_args()
    import tcd
    tcd.init("cpu", "f64")
    pts = pyramid(a.shape, a.radius, a.drop, a.spacing)
    m = mirror_partner(pts)
    for name in a.solver or SOLVERS:
        first = run(pts, np.arange(len(pts)), a.radius, a.friction, a.steps, a.tolerance,
                    SOLVERS[name])
        second = (run(pts, m, a.radius, a.friction, a.steps, a.tolerance, SOLVERS[name])
                  if a.shape == "plane" else None)
        worst = [0.0, 0.0, 0.0]
        for k, (x, w) in enumerate(first):
            ex, ew = asymmetry(x, w, m)
            line = f"{name}: step {k + 1}: off the mirror {ex:.2e} m, {ew:.2e} rad/s"
            worst[:2] = max(worst[0], ex), max(worst[1], ew)
            if second is not None:
                # the run numbered right to left against the mirror image of the first
                x2, w2 = second[k]
                dm = max(np.abs(x2 - x[m] * (-1, 1, 1)).max(), np.abs(w2 - w[m] * (1, -1, -1)).max())
                worst[2] = max(worst[2], dm)
                line += f"; mirrored numbering minus mirror image {dm:.2e}"
            print(line)
        print(f"{name}: largest over {a.steps} steps: {worst[0]:.2e} m, {worst[1]:.2e} rad/s"
              + (f", mirrored numbering {worst[2]:.2e}" if second is not None else ""))


if __name__ == "__main__":
    main()
