"""Cost model of a resident-schedule sweep on a GPU thread block (solver.solve_resident).

    python benchmarks/resident_cost_model.py [--sample PATH] [--samples K] [--threads 256,512,1024]

Runs a few steps of `tcd bench shear` with the GPU's choices (TCD_AUTO=gpu: the colouring by
rounds) on this CPU, then prices one sweep over the last step's colour lists: within a colour,
thread t of a block of T visits the items t, t + T, ... of its system, and the colour ends when
its busiest thread does (a barrier), so a sweep costs the sum over colours of the busiest
thread's work. Work is counted in bond visits: a contact 2, a particle block with k bonds
1 + 2k (the two passes of solver.solve_particle_bonds). "heaviest first" prices the same lists
sorted by cost inside each colour (the order inside a colour changes no number). The lower
bound is the sum over colours of the largest item: what any number of threads leaves.

Session 38, seed-1 shear (21 colours, 63570 units per sweep, at most 17 bonds per particle):
486 units with 256 threads, 351 with 512, 333 with 1024, lower bound 333; sorted, 468 with
256 and nothing with more. The five samples batched (28 colours; each block waits for its
slowest system): 545 / 406 / 386 for the slowest. The H200 measured 1.7 ms per plain sweep of
the seed-1 shear with 256 threads.
"""
import argparse
import os
import sys

os.environ.setdefault("TCD_AUTO", "gpu")
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import numpy as np  # noqa: E402

from tcd import bench  # noqa: E402


def sweep_costs(sim, threads) -> dict:
    cs, bd = sim.colours, sim.bonds
    n, nsys = sim.n, sim.systems
    ncol = int(sim.stats.colours[None])
    order, ss = cs.order.to_numpy(), cs.sys_start.to_numpy()
    start, rev = bd.start.to_numpy(), bd.rev_start.to_numpy()
    k = (start[1:n + 1] - start[:n]) + (rev[1:n + 1] - rev[:n])
    if not sim.settings.bond_blocks:
        raise SystemExit("the model prices particle blocks (bond_blocks = true) only")

    def cost(items):
        return np.where(items < n, 1 + 2 * k[np.minimum(items, n - 1)], 2)

    out = {"colours": ncol, "systems": nsys, "max_bonds": int(k.max())}
    for T in threads:
        for mode in ("as listed", "heaviest first"):
            per_system = np.zeros(nsys)
            for c in range(ncol):
                for sy in range(nsys):
                    w = cost(order[ss[c * nsys + sy]:ss[c * nsys + sy + 1]])
                    if mode == "heaviest first":
                        w = np.sort(w)[::-1]
                    busy = np.zeros(T)
                    np.add.at(busy, np.arange(len(w)) % T, w)
                    per_system[sy] += busy.max()
            out[f"{T} threads, {mode}"] = per_system.round().astype(int).tolist()
    bound = np.zeros(nsys)
    units = np.zeros(nsys)
    for c in range(ncol):
        for sy in range(nsys):
            w = cost(order[ss[c * nsys + sy]:ss[c * nsys + sy + 1]])
            if len(w):
                bound[sy] += w.max()
                units[sy] += w.sum()
    out["units per sweep"] = units.astype(int).tolist()
    out["lower bound"] = bound.astype(int).tolist()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sample", default="samples/leutner_seed1_prepared.h5")
    ap.add_argument("--samples", type=int, default=1)
    ap.add_argument("--threads", default="256,512,1024")
    args = ap.parse_args()
    threads = [int(t) for t in args.threads.split(",")]
    result = {}
    loop = bench._loop

    def priced_loop(sim, steps, per_system=False):
        out = loop(sim, steps, per_system)
        result.update(sweep_costs(sim, threads))
        return out
    bench._loop = priced_loop
    bench.shear(sample=args.sample, samples=args.samples, time=0.001, schedule="resident")
    for key, value in result.items():
        print(f"{key}: {value}")


if __name__ == "__main__":
    main()
