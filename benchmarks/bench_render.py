"""Benchmark of the offscreen renderer on an asphalt-like sample.

5200 spheres of radii 1, 2.8, 4, 5.6, 8 mm (number fractions 45/25/15/10/5 %) placed by seeded
random sequential addition (overlaps tolerated when no free site is found quickly) in a 75 mm
radius, 120 mm high cylinder; two layers split at mid-height. Renders 1600 x 1200 and prints the
time of the first call (kernel compilation included) and of the following calls (compile
excluded). Usage: python benchmarks/bench_render.py [--arch cpu] [--precision f64] [--out PNG]
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout
import tcd  # noqa: E402
from tcd import render  # noqa: E402

RADII = np.array([1.0, 2.8, 4.0, 5.6, 8.0]) * 1e-3
FRACTIONS = np.array([0.45, 0.25, 0.15, 0.10, 0.05])
CYL_RADIUS, CYL_HEIGHT = 0.075, 0.120


def sample(n=5200, seed=1, tries=15):
    """Positions (n,3) m, radii (n,), layer (n,) of a loose random packing in the cylinder."""
    rng = np.random.default_rng(seed)
    radius = np.sort(rng.choice(RADII, size=n, p=FRACTIONS))[::-1]
    cell = 2 * RADII.max()
    grid = {}
    x = np.zeros((n, 3))
    for i, r in enumerate(radius):
        best, best_overlap = None, np.inf
        for _ in range(tries):
            rho = (CYL_RADIUS - r) * np.sqrt(rng.random())
            phi = 2 * np.pi * rng.random()
            p = np.array([rho * np.cos(phi), rho * np.sin(phi), r + (CYL_HEIGHT - 2 * r) * rng.random()])
            key = tuple((p // cell).astype(int))
            near = [k for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
                    for k in grid.get((key[0] + dx, key[1] + dy, key[2] + dz), ())]
            overlap = 0.0
            if near:
                near = np.array(near)
                overlap = float(np.max(radius[near] + r - np.linalg.norm(x[near] - p, axis=1)))
            if overlap < best_overlap:
                best, best_overlap = p, overlap
            if overlap <= 0.0:
                break
        x[i] = best
        grid.setdefault(tuple((best // cell).astype(int)), []).append(i)
    layer = (x[:, 2] > 0.5 * CYL_HEIGHT).astype(np.int32)
    return x, radius, layer


def walls():
    return render.WallSet(
        kind=np.array([render.PLANE, render.PLANE, render.CYLINDER]),
        point=np.array([[0, 0, 0], [0, 0, CYL_HEIGHT], [0, 0, 0]], float),
        direction=np.array([[0, 0, 1], [0, 0, -1], [0, 0, 1]], float),
        radius=np.full(3, CYL_RADIUS), extent=np.array([[0, 0], [0, 0], [0, CYL_HEIGHT]]))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--arch", default="cpu", choices=("cpu", "gpu"))
    parser.add_argument("--precision", default="f64", choices=("f64", "f32"))
    parser.add_argument("--width", type=int, default=1600)
    parser.add_argument("--height", type=int, default=1200)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", default="renders/render_bench_sample.png")
    args = parser.parse_args()
    tcd.init(args.arch, args.precision)

    t = time.perf_counter()
    x, radius, layer = sample()
    print(f"sample: {len(x)} spheres generated in {time.perf_counter() - t:.1f} s")
    frame = {"x": x, "radius": radius, "layer": layer, "time": 0.0, "stage": "bench"}
    colors, _ = render.particle_colors(frame, "layer")
    kw = dict(width=args.width, height=args.height, walls=walls(), camera="iso")

    t = time.perf_counter()
    render.render_scene(x, radius, colors, **kw)
    first = time.perf_counter() - t
    times = []
    for _ in range(args.repeat):
        t = time.perf_counter()
        image = render.render_scene(x, radius, colors, **kw)
        times.append(time.perf_counter() - t)
    t = time.perf_counter()
    render.render_scene(x, radius, colors, section="xz", **kw)
    section_time = time.perf_counter() - t
    print(f"render {args.width}x{args.height}, {len(x)} spheres, arch={args.arch}, "
          f"precision={args.precision}")
    print(f"  first call (compile included): {first:.2f} s")
    print(f"  next calls (compile excluded): best {min(times):.2f} s, median "
          f"{float(np.median(times)):.2f} s over {len(times)}")
    print(f"  xz section view: {section_time:.2f} s")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        render.write_image(image, args.out)
        print(f"  wrote {args.out}")


if __name__ == "__main__":
    main()
