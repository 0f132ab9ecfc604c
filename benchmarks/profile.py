"""Where the time of a step goes, kernel by kernel (Taichi's kernel profiler).

    python benchmarks/profile.py pour  --particles 2600 --time 0.1 [--arch gpu]
    python benchmarks/profile.py shear --sample samples/leutner_seed1_prepared.h5 --time 0.01

Runs `tcd bench pour` or `tcd bench shear` with TCD_KERNEL_PROFILER=1 and prints the bench
figures, then the profiler's table (total time per kernel, launches, mean). The profiler
synchronises after every launch, so the bench figure of a profiled run is pessimistic: use it
for the split between kernels, and the plain `tcd bench` for the figure.
"""
import argparse
import json
import os
import sys

os.environ["TCD_KERNEL_PROFILER"] = "1"
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import taichi as ti  # noqa: E402

from tcd import bench  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("benchmark", choices=("pour", "shear"))
    ap.add_argument("--particles", type=int, default=None)
    ap.add_argument("--time", type=float, default=0.1)
    ap.add_argument("--arch", default="cpu", choices=("cpu", "gpu"))
    ap.add_argument("--precision", default="f64", choices=("f64", "f32"))
    ap.add_argument("--sample", default=None)
    ap.add_argument("--samples", type=int, default=1)
    ap.add_argument("--schedule", default="auto")
    ap.add_argument("--top", type=int, default=25, help="kernels listed")
    a = ap.parse_args()
    if a.benchmark == "pour":
        out = bench.pour(a.particles or 2600, a.time, a.arch, a.precision, schedule=a.schedule)
    else:
        out = bench.shear(a.particles or 5200, a.time, a.arch, a.precision, sample=a.sample,
                          samples=a.samples, schedule=a.schedule)
    print(json.dumps({k: v for k, v in out.items() if k != "per_sample"}))
    kp = ti.profiler.kernel_profiler.get_default_kernel_profiler()
    kp._update_records()
    rows = {}
    for rec in kp._traced_records:
        t, c = rows.get(rec.name, (0.0, 0))
        rows[rec.name] = (t + rec.kernel_time, c + 1)
    total = sum(t for t, _ in rows.values()) or 1.0
    print(f"kernel time {total / 1e3:.3f} s in all (profiler)")
    print(f"{'kernel':60s} {'ms':>10s} {'share':>6s} {'calls':>8s} {'us/call':>9s}")
    for name, (t, c) in sorted(rows.items(), key=lambda kv: -kv[1][0])[:a.top]:
        print(f"{name[:60]:60s} {t:10.1f} {100 * t / total:5.1f}% {c:8d} {1e3 * t / c:9.1f}")


if __name__ == "__main__":
    main()
