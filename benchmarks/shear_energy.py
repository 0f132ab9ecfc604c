"""Energy audit of the shear stage: where does the kinetic energy of a quasi-static test come from?

Runs the first STEPS steps of a scenario's shear stage (shear-only scenario with `sample = ...`)
and writes, per step: kinetic energy (translational + rotational), the work of the walls on the
grains over the step (-F.v_wall H summed over the walls; F is the force the grains exert on a
wall), bonds broken so far, sweeps, residual, shear stress and the fastest grain's speed and
height. Usage:

    python benchmarks/shear_energy.py scenarios/calibration_seed1.toml --steps 1500 \
        --tolerance 1e-6 --out runs/energy_tol1e-6.csv
"""
from __future__ import annotations

import argparse
import csv
import pathlib
import re
import sys
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--tolerance", type=float, default=None)
    ap.add_argument("--max-sweeps", type=int, default=None)
    ap.add_argument("--set", action="append", default=[],
                    help="override a scenario line KEY=VALUE (first `KEY = ...` line replaced)")
    ap.add_argument("--energy", action="store_true",
                    help="also the potential energy of gravity and the bonds' elastic energy")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)

    from tcd import backend, laws
    from tcd.config import parse_scenario
    from tcd.protocols import Shear
    from tcd.runner import load_prepared

    path = pathlib.Path(a.scenario)
    text = path.read_text()
    sets = list(a.set)
    if a.tolerance is not None:
        sets.append(f"tolerance={a.tolerance!r}")
    if a.max_sweeps is not None:
        sets.append(f"max_sweeps={a.max_sweeps}")
    for kv in sets:
        key, value = kv.split("=", 1)
        text, n = re.subn(rf"(?m)^{re.escape(key.strip())}\s*=.*$", f"{key.strip()} = {value.strip()}", text, count=1)
        if n == 0:
            sys.exit(f"--set {kv}: no `{key} = ...` line in {path}")
    scn = parse_scenario(text, str(path))
    backend.init(scn.backend.arch, scn.backend.precision)
    stage = [s for s in scn.stages if s.kind == "shear"][0]
    sim = load_prepared(scn, stage.sample)
    proto = Shear(stage, scn, scn.seeds[0])
    phase, sim = proto.plan(0, sim, sim.time)
    sim.set_walls(phase.walls)
    h = scn.solver.time_step
    r = sim.radii()
    m = scn.material.density * 4.0 / 3.0 * np.pi * r**3
    inertia = 0.4 * m * r**2
    law = sim.bond_law
    g = scn.solver.gravity

    def bond_energy():
        """Elastic energy of the intact bonds (secant or Burgers spring about its offset)."""
        st = sim.state_dict()
        ok = st["bonds/state"] == 0
        i, j = st["bonds/i"][ok], st["bonds/j"][ok]
        x = st["particles/x"]
        dn = np.linalg.norm(x[j] - x[i], axis=1) - r[i] - r[j] - st["bonds/g0"][ok]
        dt = st["bonds/d_t"][ok]
        if law.mode == "paper":
            comp = laws.creep_compliance(sim.time - st["bonds/created"][ok], law.maxwell_stiffness,
                                         law.maxwell_viscosity, law.kelvin_stiffness, law.kelvin_viscosity)
        else:
            comp = np.full(len(i), 1.0 / law.maxwell_stiffness)
        return float(np.sum(0.5 * dn**2 / comp + 0.5 * (dt**2).sum(1) / (comp * law.tangent_factor)))

    rows = []
    t0 = time.perf_counter()
    work = 0.0
    for k in range(a.steps):
        t_beg = sim.time
        proto.before_step(sim, phase)
        rec = sim.step()
        dw = 0.0
        for iw, w in enumerate(sim.walls):
            vw = w.step_velocity(t_beg, h)
            dw -= float(np.dot(sim.wall_force(iw), vw)) * h
        work += dw
        v, om, x = sim.velocities(), sim.angular_velocities(), sim.positions()
        ke_t = 0.5 * float((m * (v**2).sum(1)).sum())
        ke_r = 0.5 * float((inertia * (om**2).sum(1)).sum())
        sp = np.linalg.norm(v, axis=1)
        f = int(sp.argmax())
        counts = sim.bonds_state_counts()
        extra = {}
        if a.energy:
            extra = {"pe": float((m * g * x[:, 2]).sum()), "e_bond": bond_energy()}
        rows.append({"step": k + 1, "time": sim.time, "ke_trans": ke_t, "ke_rot": ke_r, **extra,
                     "wall_work_step": dw, "wall_work_total": work,
                     "bonds_broken": counts[1] + counts[2], "sweeps": rec.sweeps,
                     "residual": rec.residual, "contacts": rec.contacts,
                     "shear_stress": float(-sim.wall_force(2)[0] / (np.pi * phase.info["radius"] ** 2)),
                     "vmax": float(sp[f]), "vmax_z": float(x[f, 2]), "vmax_r": float(np.hypot(*x[f, :2]))})
        if (k + 1) % 100 == 0:
            row = rows[-1]
            print(f"step {k + 1} ke={row['ke_trans']:.3e}+{row['ke_rot']:.3e} W={work:.3e} "
                  f"broken={row['bonds_broken']} sweeps={rec.sweeps} res={rec.residual:.1e} "
                  f"tau={row['shear_stress'] * 1e-6:.3f} vmax={row['vmax']:.3e}@z={row['vmax_z'] * 1e3:.1f}mm "
                  f"{time.perf_counter() - t0:.0f}s", flush=True)
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", newline="") as fh:
        wr = csv.DictWriter(fh, fieldnames=list(rows[0]))
        wr.writeheader()
        wr.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
