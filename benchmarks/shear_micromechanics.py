"""Micromechanics of a Leutner shear: `tcd analyse` over the shear snapshots of one sample, plotted
against the ring's displacement next to the measured shear stress.

    python benchmarks/shear_micromechanics.py RUN_DIR/sample_1 --out renders/shear_micromechanics_seed1.png

Reads SAMPLE_DIR/states.h5 (frames of the shear stage) and SAMPLE_DIR/shear_series.h5, writes
SAMPLE_DIR/micromechanics.h5/.csv (tcd analyse) and the figure: (a) the shear stress on the ring
and the Love-Weber stress in the grains (xz, xx, zz) times the packing fraction, i.e. over the
sample's volume (sigma_xx, sigma_zz as compressions); (b) the fabric tensor's anisotropy and xz term; (c) intact bonds and contacts.
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))     # run from a checkout
from tcd import analysis, io  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sample_dir")
    ap.add_argument("--out", required=True, help="figure (.png)")
    a = ap.parse_args(argv)
    d = pathlib.Path(a.sample_dir)
    states = d / "states.h5"
    count = io.frame_count(states)
    shear = [k for k in range(count) if io.read_frame(states, k)["stage"].endswith("shear")]
    if len(shear) < 2:
        raise SystemExit(f"{states}: fewer than two shear frames")
    h5, _ = analysis.analyse(states, d / "micromechanics", frames=shear)
    m = io.read_series(h5)
    s = io.read_series(d / "shear_series.h5")
    # packing fraction of the sample between the plates, from the first shear frame's walls
    f0 = io.read_frame(states, shear[0])
    kind, point, radius = f0["walls/kind"], f0["walls/point"], f0["walls/radius"]
    planes = point[kind == io.WALL_PLANE][:, 2]
    R = float(radius[kind == io.WALL_CYLINDER].max())
    r = f0["particles/radius"]
    phi = float(np.sum(4 / 3 * np.pi * r**3) / (np.pi * R**2 * (planes.max() - planes.min())))
    disp = np.interp(m["time"], s["time"], s["displacement"]) * 1e3

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(3, 1, figsize=(7, 9), sharex=True)
    ax[0].plot(s["displacement"] * 1e3, s["shear_stress"] * 1e-6, color="0.6", lw=0.8,
               label="shear stress on the ring (force / section)")
    ax[0].plot(disp, phi * m["stress_xz"] * 1e-6, "-o", ms=3,
               label="phi sigma_xz: the grains' shear stress averaged over the sample")
    for comp, style in (("xx", "--s"), ("zz", ":^")):
        ax[0].plot(disp, -phi * m[f"stress_{comp}"] * 1e-6, style, ms=3,
                   label=f"-phi sigma_{comp} (compression positive)")
    ax[0].set_ylabel("MPa")
    ax[0].legend(fontsize=7, loc="upper left")
    ax[1].plot(disp, m["fabric_anisotropy"], "-o", ms=3, label="fabric anisotropy (l1 - l3)")
    ax[1].plot(disp, m["fabric_xz"], "--s", ms=3, label="fabric xz")
    ax[1].legend(fontsize=7)
    ax[2].plot(disp, m["bonds_intact"], "-o", ms=3, label="intact bonds")
    ax[2].plot(disp, m["contacts"], "--s", ms=3,
               label="frictional contacts (the bonded pairs leave them at the start)")
    ax[2].legend(fontsize=7)
    ax[2].set_xlabel("ring displacement (mm)")
    fig.suptitle(f"Micromechanics of the Leutner shear ({d.name}, packing {phi:.3f} between the plates)", fontsize=9)
    fig.tight_layout()
    out = pathlib.Path(a.out)
    with io.atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=130, format="png")
    print(f"wrote {out} and {h5}")
    for k in range(len(disp)):
        print(f"{disp[k]:6.2f} mm  sigma_xz {m['stress_xz'][k]:10.0f} Pa  zz {m['stress_zz'][k]:10.0f}"
              f"  fabric_an {m['fabric_anisotropy'][k]:.4f}  xz {m['fabric_xz'][k]:+.4f}"
              f"  bonds {m['bonds_intact'][k]}  contacts {m['contacts'][k]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
