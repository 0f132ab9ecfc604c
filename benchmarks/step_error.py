"""How far a step stopped at the solver's tolerance lies from the same step solved to
convergence, at several time steps, from one state of a run.

The solver stops a step when a sweep changes the impulses by less than the tolerance
(sum |dR| / sum |R|, PHYSICS.md section 6). That is a measure of the last sweep's change, not
of the distance to the step's solution: on a stiff bonded network Gauss-Seidel converges
slowly, so a small change per sweep may leave the step far from its solution. This script
measures that distance. From a run's checkpoint (any `tcd run` sample's checkpoint.h5, with
its scenario), for each time step H: `--settle-steps` steps at (H, tolerance), so that the warm
start is that of a run at H; then the next step twice from the same state, once at the
tolerance and once at `--reference-tolerance` (up to `--reference-sweeps` sweeps); and the
differences between the two, relative to the reference:

- impulse: all bond and contact impulses (one vector), 2-norm; bonds: the bonds' alone;
- velocity: the grains' velocities, 2-norm (loose grains, whose velocity the converged step
  sets freely, weigh in it), and per grain in mm/s: the median and 99th percentile of the
  difference, next to the converged step's median speed;
- wall force: the x force on the moving walls (the shear's upper ring and top plate).

    python benchmarks/step_error.py RUN/sample_1/checkpoint.h5 SCENARIO.toml
        [--time-steps 2e-4,1e-4,5e-5,2.5e-5] [--tolerance 1e-5] [--settle-steps 20]
        [--reference-tolerance 1e-12] [--reference-sweeps 100000] [--json]

Session 52, the seed-1 shear at 1.0 mm (the study's scenario at H = 2e-4 s, tolerance 1e-5),
tolerance 1e-5: the step's impulses are 2.2 % from the converged step's at H = 2e-4 s
(17 sweeps), 1.9 % at 1e-4 (11 sweeps), 0.41 % at 5e-5 (9 sweeps); the ring force 0.10 %,
0.02 %, 0.002 % (docs/results.md, "Time step and tolerance").
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout


def _solve_once(sim, d, t, k, tolerance, max_sweeps):
    """The next step from state `d` at clock `t`, step `k`: its record and what is compared."""
    sim.load_state_dict(d)
    sim.time, sim.step_index = t, k
    sim.settings = dataclasses.replace(sim.settings, tolerance=tolerance, max_sweeps=max_sweeps)
    rec = sim.step()
    s = sim.state_dict()
    moving = [w for w, wall in enumerate(sim.walls) if wall.motion != "fixed"]
    return rec, {"pairs": np.concatenate([s["contacts/i"], s["contacts/j"]]),
                 "bonds": s["bonds/impulse"].ravel(), "contacts": s["contacts/impulse"].ravel(),
                 "v": sim.velocities(),
                 "force": float(sum(sim.wall_force(w)[0] for w in moving))}


def _relative(a, b) -> float:
    scale = float(np.linalg.norm(b))
    return float(np.linalg.norm(a - b)) / scale if scale > 0 else float(np.linalg.norm(a - b))


def _per_grain(v, v_ref) -> dict:
    """Each grain's velocity difference and the converged step's speeds, in mm/s."""
    dv = np.linalg.norm(v - v_ref, axis=1) * 1e3
    return {"velocity_error_median_mm_s": float(np.median(dv)),
            "velocity_error_p99_mm_s": float(np.quantile(dv, 0.99)),
            "reference_speed_median_mm_s": float(np.median(np.linalg.norm(v_ref, axis=1)) * 1e3)}


def step_error(sim, time_step: float, tolerance: float, *, settle_steps: int = 20,
               reference_tolerance: float = 1e-12, reference_sweeps: int = 100000,
               max_sweeps: int | None = None) -> dict:
    """Run `settle_steps` steps of `sim` at (time_step, tolerance), then compare its next step
    at the tolerance with the same step at the reference tolerance (see the module's
    docstring). `sim` is left after the reference step."""
    cap = max_sweeps or sim.settings.max_sweeps
    sim.settings = dataclasses.replace(sim.settings, time_step=time_step, tolerance=tolerance,
                                       max_sweeps=cap)
    for _ in range(settle_steps):
        sim.step()
    d, t, k = sim.state_dict(), sim.time, sim.step_index
    rec, a = _solve_once(sim, d, t, k, tolerance, cap)
    ref, b = _solve_once(sim, d, t, k, reference_tolerance, reference_sweeps)
    if not np.array_equal(a["pairs"], b["pairs"]):
        raise RuntimeError("the two solves of one step built different contact lists")
    return {"time_step": time_step, "tolerance": tolerance, "sweeps": rec.sweeps,
            "residual": rec.residual, "reference_sweeps": ref.sweeps,
            "reference_residual": ref.residual,
            "impulse_error": _relative(np.concatenate([a["bonds"], a["contacts"]]),
                                       np.concatenate([b["bonds"], b["contacts"]])),
            "bond_impulse_error": _relative(a["bonds"], b["bonds"]),
            "velocity_error": _relative(a["v"], b["v"]),
            **_per_grain(a["v"], b["v"]),
            "wall_force_error": (a["force"] - b["force"]) / b["force"] if b["force"] else 0.0,
            "wall_force_N": b["force"]}


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint", help="a run's checkpoint.h5 (tcd run ... writes one per sample)")
    ap.add_argument("scenario", help="the scenario file of that run")
    ap.add_argument("--time-steps", default="2e-4,1e-4,5e-5,2.5e-5")
    ap.add_argument("--tolerance", type=float, default=1e-5)
    ap.add_argument("--settle-steps", type=int, default=20)
    ap.add_argument("--reference-tolerance", type=float, default=1e-12)
    ap.add_argument("--reference-sweeps", type=int, default=100000)
    ap.add_argument("--arch", default="cpu", choices=["cpu", "gpu"])
    ap.add_argument("--json", action="store_true", help="one JSON object per time step")
    a = ap.parse_args(argv)
    import tcd
    tcd.init(a.arch, "f64")
    from tcd import config, io, runner
    # its solver, material and bond tables (its samples need not be where they were)
    scn = config.parse_scenario(Path(a.scenario).read_text(), a.scenario, resolve_samples=False)
    arrays, meta = io.load_checkpoint(a.checkpoint)
    rows = []
    if not a.json:
        print("| H (s) | sweeps | impulse error | bond impulse error | velocity error "
              "| per grain, median / 99th percentile (mm/s; converged median speed) "
              "| wall force error | reference sweeps, residual |")
        print("|---|---|---|---|---|---|---|---|")
    for h in (float(v) for v in a.time_steps.split(",")):
        sim = runner.restore_simulation(scn, arrays, meta)
        row = step_error(sim, h, a.tolerance, settle_steps=a.settle_steps,
                         reference_tolerance=a.reference_tolerance,
                         reference_sweeps=a.reference_sweeps)
        sim.close()
        rows.append(row)
        if a.json:
            print(json.dumps(row), flush=True)
        else:
            print(f"| {h:g} | {row['sweeps']} | {row['impulse_error']:.2e} | "
                  f"{row['bond_impulse_error']:.2e} | {row['velocity_error']:.2e} | "
                  f"{row['velocity_error_median_mm_s']:.3g} / {row['velocity_error_p99_mm_s']:.3g} "
                  f"({row['reference_speed_median_mm_s']:.3g}) | "
                  f"{row['wall_force_error']:+.2e} | {row['reference_sweeps']}, "
                  f"{row['reference_residual']:.1e} |", flush=True)
    return rows


if __name__ == "__main__":
    main()
