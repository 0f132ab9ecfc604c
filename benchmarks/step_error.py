"""How far a step stopped at the solver's tolerance lies from the same step solved to
convergence, at several time steps and tolerances, from one state of a run.

The solver stops a step when a sweep changes the impulses by less than the tolerance
(sum |dR| / sum |R|, PHYSICS.md section 6). That is a measure of the last sweep's change, not
of the distance to the step's solution: on a stiff bonded network Gauss-Seidel converges
slowly, so a small change per sweep may leave the step far from its solution. This script
measures that distance. From a run's checkpoint (any `tcd run` sample's checkpoint.h5, with
its scenario), for each time step H: `--settle-steps` steps at H and the settling tolerance
(`--settle-tolerance`, by default the first of `--tolerance`), so that the warm start is that
of a run at H; then the next step from the same state once at `--reference-tolerance` (up to
`--reference-sweeps` sweeps) and once at each tolerance (up to `--max-sweeps`, by default the
scenario's cap); and the differences between each and the reference, relative to it:

- impulse: all bond and contact impulses (one vector), 2-norm; bonds: the bonds' alone; and
  the 1 % most loaded bonds (those a break takes first): the median and largest relative
  difference of their force;
- velocity: the grains' velocities, 2-norm (loose grains, whose velocity the converged step
  sets freely, weigh in it); per grain in mm/s: the median and 99th percentile of the
  difference, next to the converged step's median speed, and the mass-weighted RMS; and the
  energy norm |M^1/2 dv| (translations and rotations) over that of the converged step's own
  velocity change (v+ - v- - H (g + f/m)): near 0 for an error that moves no grain (a
  self-stress), about 1 for one as large as the step;
- wall force: the x force on the moving walls (the shear's upper ring and top plate).

    python benchmarks/step_error.py RUN/sample_1/checkpoint.h5 SCENARIO.toml
        [--time-steps 2e-4,1e-4,5e-5,2.5e-5] [--tolerance 1e-5[,1e-6,...]] [--settle-steps 20]
        [--settle-tolerance TOL] [--max-sweeps N] [--convergence impulse|quad]
        [--reference-tolerance 1e-12]
        [--reference-sweeps 100000] [--json]

Session 52, the seed-1 shear at 1.0 mm (the study's scenario at H = 2e-4 s, tolerance 1e-5),
tolerance 1e-5: the step's impulses are 2.2 % from the converged step's at H = 2e-4 s
(17 sweeps), 1.9 % at 1e-4 (11 sweeps), 0.41 % at 5e-5 (9 sweeps); the ring force 0.10 %,
0.02 %, 0.002 % (docs/results.md, "Time step and tolerance"). Session 56, the same state,
`--time-steps 2e-4 --tolerance 1e-5,1e-6,1e-7 --max-sweeps 200000 --reference-tolerance 1e-13
--reference-sweeps 60000`: per grain 0.63 / 0.26 / 0.10 mm/s at the median (the ring moves at
0.833), energy norm 1.04 / 0.32 / 0.14 of the step's (docs/results.md, "What the tolerance
leaves in the grains' velocities").
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))     # run from a checkout


def _solve_once(sim, d, t, k, tolerance, max_sweeps, convergence=None):
    """The next step from state `d` at clock `t`, step `k` (stopped by the `convergence`
    measure, by default the settings'): its record and what is compared."""
    sim.load_state_dict(d)
    sim.time, sim.step_index = t, k
    sim.settings = dataclasses.replace(sim.settings, tolerance=tolerance, max_sweeps=max_sweeps,
                                       convergence=convergence or sim.settings.convergence)
    rec = sim.step()
    s = sim.state_dict()
    moving = [w for w, wall in enumerate(sim.walls) if wall.motion != "fixed"]
    return rec, {"pairs": np.concatenate([s["contacts/i"], s["contacts/j"]]),
                 "bonds": s["bonds/impulse"].ravel(), "contacts": s["contacts/impulse"].ravel(),
                 "v": sim.velocities(), "w": sim.angular_velocities(),
                 "force": float(sum(sim.wall_force(w)[0] for w in moving))}


def _relative(a, b) -> float:
    scale = float(np.linalg.norm(b))
    return float(np.linalg.norm(a - b)) / scale if scale > 0 else float(np.linalg.norm(a - b))


def _per_grain(v, v_ref, m) -> dict:
    """Each grain's velocity difference (its median, 99th percentile and RMS weighted by the
    masses `m`) and the converged step's speeds, in mm/s."""
    dv = np.linalg.norm(v - v_ref, axis=1) * 1e3
    return {"velocity_error_median_mm_s": float(np.median(dv)),
            "velocity_error_p99_mm_s": float(np.quantile(dv, 0.99)),
            "reference_speed_median_mm_s": float(np.median(np.linalg.norm(v_ref, axis=1)) * 1e3),
            "velocity_error_mass_rms_mm_s": (float(np.sqrt((m * dv**2).sum() / m.sum()))
                                             if m.sum() > 0 else float("nan"))}


def _masses(inverse) -> np.ndarray:
    """Masses (or moments of inertia) from their inverses, 0 for a kinematic grain."""
    with np.errstate(divide="ignore"):
        return np.where(inverse > 0, 1.0 / inverse, 0.0)


def _energy(m, inertia, dv, dw) -> float:
    """|M^1/2 (dv, dw)|: translations and rotations."""
    return float(np.sqrt((m[:, None] * dv**2).sum() + (inertia[:, None] * dw**2).sum()))


def _loaded_bonds(bonds, bonds_ref) -> dict:
    """The median and largest relative difference of the force of the 1 % most loaded bonds
    (of the converged step); NaN without bonds."""
    if not bonds_ref.size:
        return {"loaded_bonds_error_median": float("nan"), "loaded_bonds_error_max": float("nan")}
    f = np.linalg.norm(bonds.reshape(-1, 3), axis=1)
    f_ref = np.linalg.norm(bonds_ref.reshape(-1, 3), axis=1)
    top = (f_ref >= np.quantile(f_ref, 0.99)) & (f_ref > 0)
    rel = np.abs(f[top] - f_ref[top]) / f_ref[top]
    return {"loaded_bonds_error_median": float(np.median(rel)),
            "loaded_bonds_error_max": float(rel.max())}


def step_errors(sim, time_step: float, tolerances, *, settle_steps: int = 20,
                settle_tolerance: float | None = None, reference_tolerance: float = 1e-12,
                reference_sweeps: int = 100000, max_sweeps: int | None = None,
                convergence: str | None = None) -> list[dict]:
    """Run `settle_steps` steps of `sim` at `time_step` and `settle_tolerance` (the first of
    `tolerances` by default), then compare its next step at each tolerance (stopped by the
    `convergence` measure, by default the scenario's) with the same step at the reference
    tolerance (see the module's docstring): one row per tolerance. `sim` is left after the
    last tolerance's step."""
    cap = max_sweeps or sim.settings.max_sweeps
    tolerances = [float(t) for t in tolerances]
    settle = tolerances[0] if settle_tolerance is None else settle_tolerance
    sim.settings = dataclasses.replace(sim.settings, time_step=time_step, tolerance=settle,
                                       max_sweeps=cap)
    for _ in range(settle_steps):
        sim.step()
    d, t, k = sim.state_dict(), sim.time, sim.step_index
    inv_mass, inv_inertia = sim.inverse_masses()
    m, inertia = _masses(inv_mass), _masses(inv_inertia)
    # the free velocity: what the step would give without its impulses
    v_free = (d["particles/v"] + time_step * (inv_mass > 0)[:, None]
              * (np.asarray(sim.settings.gravity, dtype=float)
                 + d["particles/f_ext"] * inv_mass[:, None]))
    measure = sim.settings.convergence
    ref, b = _solve_once(sim, d, t, k, reference_tolerance, reference_sweeps, measure)
    step = _energy(m, inertia, b["v"] - v_free, b["w"] - d["particles/w"])
    rows = []
    for tolerance in tolerances:
        rec, a = _solve_once(sim, d, t, k, tolerance, cap, convergence or measure)
        if not np.array_equal(a["pairs"], b["pairs"]):
            raise RuntimeError("the two solves of one step built different contact lists")
        dv = a["v"] - b["v"]
        rows.append({
            "time_step": time_step, "tolerance": tolerance,
            "convergence": convergence or measure, "sweeps": rec.sweeps,
            "residual": rec.residual, "reference_sweeps": ref.sweeps,
            "reference_residual": ref.residual,
            "impulse_error": _relative(np.concatenate([a["bonds"], a["contacts"]]),
                                       np.concatenate([b["bonds"], b["contacts"]])),
            "bond_impulse_error": _relative(a["bonds"], b["bonds"]),
            **_loaded_bonds(a["bonds"], b["bonds"]),
            "velocity_error": _relative(a["v"], b["v"]),
            **_per_grain(a["v"], b["v"], m),
            "energy_error_ratio": (_energy(m, inertia, dv, a["w"] - b["w"]) / step
                                   if step > 0 else float("nan")),
            "wall_force_error": (a["force"] - b["force"]) / b["force"] if b["force"] else 0.0,
            "wall_force_N": b["force"]})
    return rows


def step_error(sim, time_step: float, tolerance: float, **kwargs) -> dict:
    """:func:`step_errors` for one tolerance (its settling tolerance too): its row."""
    return step_errors(sim, time_step, [tolerance], **kwargs)[0]


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint", help="a run's checkpoint.h5 (tcd run ... writes one per sample)")
    ap.add_argument("scenario", help="the scenario file of that run")
    ap.add_argument("--time-steps", default="2e-4,1e-4,5e-5,2.5e-5")
    ap.add_argument("--tolerance", default="1e-5", help="one tolerance or several, comma-separated")
    ap.add_argument("--settle-steps", type=int, default=20)
    ap.add_argument("--settle-tolerance", type=float, default=None,
                    help="the settling steps' tolerance (default: the first of --tolerance)")
    ap.add_argument("--max-sweeps", type=int, default=None,
                    help="the sweep cap of the settling and compared steps (default: the scenario's)")
    ap.add_argument("--convergence", choices=["impulse", "quad"], default=None,
                    help="the measure that stops the compared steps (default: the scenario's; "
                    "the settling and the reference keep the scenario's)")
    ap.add_argument("--reference-tolerance", type=float, default=1e-12)
    ap.add_argument("--reference-sweeps", type=int, default=100000)
    ap.add_argument("--arch", default="cpu", choices=["cpu", "gpu"])
    ap.add_argument("--json", action="store_true", help="one JSON object per time step and tolerance")
    a = ap.parse_args(argv)
    tolerances = [float(v) for v in a.tolerance.split(",")]
    import tcd
    tcd.init(a.arch, "f64")
    from tcd import config, io, runner
    # its solver, material and bond tables (its samples need not be where they were)
    scn = config.parse_scenario(Path(a.scenario).read_text(), a.scenario, resolve_samples=False)
    arrays, meta = io.load_checkpoint(a.checkpoint)
    out = []
    if not a.json:
        print("| H (s) | tolerance | sweeps | impulse error | bond impulse error | 1 % most loaded "
              "bonds, median / largest | velocity error | per grain, median / 99th percentile "
              "(mm/s; converged median speed) | mass-weighted RMS (mm/s) | energy norm / the "
              "step's | wall force error | reference sweeps, residual |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for h in (float(v) for v in a.time_steps.split(",")):
        sim = runner.restore_simulation(scn, arrays, meta)
        rows = step_errors(sim, h, tolerances, settle_steps=a.settle_steps,
                           settle_tolerance=a.settle_tolerance, max_sweeps=a.max_sweeps,
                           convergence=a.convergence,
                           reference_tolerance=a.reference_tolerance,
                           reference_sweeps=a.reference_sweeps)
        sim.close()
        out += rows
        for row in rows:
            if a.json:
                print(json.dumps(row), flush=True)
                continue
            print(f"| {h:g} | {row['tolerance']:g} | {row['sweeps']} | "
                  f"{row['impulse_error']:.2e} | {row['bond_impulse_error']:.2e} | "
                  f"{row['loaded_bonds_error_median']:.2e} / {row['loaded_bonds_error_max']:.2e} | "
                  f"{row['velocity_error']:.2e} | "
                  f"{row['velocity_error_median_mm_s']:.3g} / {row['velocity_error_p99_mm_s']:.3g} "
                  f"({row['reference_speed_median_mm_s']:.3g}) | "
                  f"{row['velocity_error_mass_rms_mm_s']:.3g} | {row['energy_error_ratio']:.3g} | "
                  f"{row['wall_force_error']:+.2e} | {row['reference_sweeps']}, "
                  f"{row['reference_residual']:.1e} |", flush=True)
    return out


if __name__ == "__main__":
    main()
