"""Issue 6's calibration table: the settings and results of shear runs, one Markdown row per
sample of each run directory, read from the run's `scenario.toml`, `summary.json` and
`shear_series.csv` (nothing is recomputed by a simulation).

    python benchmarks/calibration_table.py runs/cal_a runs/cal_b ... [--at 0.5,1.0,1.5,2.0,2.5]

Columns: yield stress, ring friction, bond gap tolerance, solver tolerance of the shear, the
smoothed peak (stress, displacement), the raw stress at the `--at` displacements, bonds broken,
the fraction of the broken bonds near the shear plane and whether the run reached its end.
A sample still running is listed from its series so far, marked "running"; a finished sample
of a run still going on is read from its own summary.json.
"""
import argparse
import csv
import json
import pathlib
import tomllib

import numpy as np

EXPERIMENT = (0.898, 2.37)  # MPa, mm: the paper's Table 2 (mean of the experiments)


def _series(path: pathlib.Path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    head = [h.split(" [")[0] for h in rows[0]]
    data = np.array([[float(x) for x in r] for r in rows[1:]]) if len(rows) > 1 else np.zeros((0, len(head)))
    return {h: data[:, k] for k, h in enumerate(head)}


def _shear_stage(scn: dict) -> dict:
    return next(s for s in scn.get("stage", []) if s.get("kind") == "shear")


def rows_of(run: pathlib.Path, at: list[float]) -> list[list[str]]:
    scn = tomllib.loads((run / "scenario.toml").read_text())
    st = _shear_stage(scn)
    bond = scn.get("bond", {})
    tol = st.get("tolerance", scn.get("solver", {}).get("tolerance", 1e-4))
    settings = [f"{bond.get('yield_stress_MPa', 2.7):g}", f"{st.get('wall_friction', 0.0):g}",
                f"{bond.get('gap_tolerance_mm', 0.01):g}", f"{tol:g}"]
    summary = {}
    if (run / "summary.json").exists():
        summary = {s["seed"]: s for s in json.loads((run / "summary.json").read_text())["samples"]}
    out = []
    for sample in sorted(run.glob("sample_*")):
        seed = int(sample.name.split("_")[1])
        ser = _series(sample / "shear_series.csv") if (sample / "shear_series.csv").exists() else None
        d_mm = ser["displacement"] * 1e3 if ser is not None else np.zeros(0)
        tau = ser["shear_stress"] * 1e-6 if ser is not None else np.zeros(0)
        raw = []
        for d in at:
            k = np.searchsorted(d_mm, d - 1e-9)
            raw.append(f"{tau[k]:.3f}" if k < len(tau) else "")
        own = sample / "summary.json"         # a finished sample of a run still going on
        if seed not in summary and own.exists():
            summary[seed] = json.loads(own.read_text())
        s = summary.get(seed, {}).get("stages", {})
        sh = next((v for k, v in s.items() if k.endswith(":shear")), None)
        if sh:
            peak = f"{sh['tau_peak_MPa']:.3f} at {sh['d_peak_mm']:.2f}"
            broken = f"{sh['bonds_broken']} / {sh['bonds_total']}"
            near = f"{sh['broken_near_plane_fraction']:.2f}"
            state = "done"
        else:
            peak, broken, near = "", "", ""
            state = f"running ({d_mm[-1]:.2f} mm)" if len(d_mm) else "running"
        out.append([run.name, str(seed), *settings, peak, *raw, broken, near, state])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="run directories (each with scenario.toml and sample_N/)")
    ap.add_argument("--at", default="0.5,1.0,1.5,2.0,2.37,2.5",
                    help="displacements (mm) at which to list the raw stress (default %(default)s)")
    args = ap.parse_args(argv)
    try:
        at = [float(x) for x in args.at.split(",")]
    except ValueError:
        ap.error(f"--at: expected comma-separated numbers in mm, got {args.at!r}")
    head = ["run", "seed", "yield (MPa)", "ring friction", "gap tol (mm)", "solver tol",
            "peak (MPa at mm)", *[f"{d:g} mm" for d in at], "bonds broken", "near plane", "state"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for run in args.runs:
        path = pathlib.Path(run)
        if not (path / "scenario.toml").exists():
            ap.error(f"{run}: not a run directory (no scenario.toml)")
        for row in rows_of(path, at):
            print("| " + " | ".join(row) + " |")
    print(f"| experiments | | | | | | {EXPERIMENT[0]} at {EXPERIMENT[1]} |" + " |" * (len(at) + 3))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
