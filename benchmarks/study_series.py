"""Per-step sweeps and residual of each sample of an interrupted `tcd run --batch`, from its
checkpoint, as CSV (one row per step: step, then sweeps and residual of each seed):

    python benchmarks/study_series.py RUN_DIR/batch_checkpoint.h5 > series.csv

For a device run whose checkpoint is too large to bring back (benchmarks/gpu_check.sh)."""
import pathlib
import sys

import h5py
import numpy as np


def main(path: str) -> None:
    if not pathlib.Path(path).is_file():
        sys.exit(f"{path}: no such file (the run wrote no checkpoint)")
    with h5py.File(path, "r") as f:
        series = f["arrays/series"]
        seeds = sorted(series, key=int)
        cols = {s: (series[s]["sweeps"][()], series[s]["residual"][()]) for s in seeds}
    steps = min(len(c[0]) for c in cols.values())
    print("step," + ",".join(f"sweeps_{s},residual_{s}" for s in seeds))
    for k in range(steps):
        print(f"{k + 1}," + ",".join(f"{int(cols[s][0][k])},{float(cols[s][1][k]):.4e}" for s in seeds))
    if steps:
        worst = np.max([cols[s][0][:steps] for s in seeds], axis=0)
        print(f"# {steps} steps; mean sweeps per sample "
              + " ".join(f"{s}:{cols[s][0][:steps].mean():.2f}" for s in seeds)
              + f"; the slowest sample's per step {worst.mean():.2f}", file=sys.stderr)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
