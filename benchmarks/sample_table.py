"""Issue 5's table of prepared samples: the numbers `Prepare.finish` reports, recomputed from
the prepared state files (so samples prepared by an older tcd get today's definitions).

    python benchmarks/sample_table.py scenarios/leutner_prepare.toml samples/leutner_seed*_prepared.h5

Prints one Markdown row per sample, the mean, and the paper's / the issue's targets; `--json`
writes the numbers as JSON too.
"""
import argparse
import json
import pathlib
import re

import numpy as np

from tcd import backend, config, io, runner
from tcd.protocols import Prepare


def sample_numbers(scn, path: pathlib.Path) -> dict:
    stage = next(s for s in scn.stages if s.kind == "prepare")
    m = re.search(r"(?:seed|sample)_?(\d+)", str(path))
    seed = int(m.group(1)) if m else 0
    sim = runner.load_prepared(scn, path)
    _, meta = io.load_checkpoint(path)
    # the phase records of the preparation (files made since session 29) give the courses
    # as built; older files have none
    numbers = Prepare(stage, scn, seed).finish(sim, meta.get("phases") or ())
    sim.close()
    return {"seed": seed, "file": str(path), **numbers}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", help="the scenario that prepared the samples (mould, heights)")
    ap.add_argument("samples", nargs="+", help="prepared.h5 files")
    ap.add_argument("--json", metavar="FILE", help="also write the numbers to FILE")
    ap.add_argument("--precision", default="f64", choices=("f64", "f32"),
                    help="Taichi's precision for the numbers (default f64)")
    args = ap.parse_args(argv)
    scn = config.load_scenario(args.scenario)
    backend.init("cpu", args.precision)
    rows = [sample_numbers(scn, pathlib.Path(p)) for p in args.samples]
    print("| seed | particles (binder + surface) | diameter, height (mm) | layer heights, equal-volume interface (mm) | "
          "packing per layer (slabs) | packing | largest overlap / d_min | outside | "
          "coordination (pairs within the alert distance / carrying a force) | "
          "course lifts, 99th-percentile tops (mm) | packing per lift (own grains) | "
          "surface grains below the binder's top (deepest, mm) | courses as built (mm) | "
          "courses as built, by their highest grain (mm) | courses by their highest grain (mm) | "
          "grains' top, gap to the plate (mm) | packing below the grains' top |")
    print("|---" * 17 + "|")
    fmt = lambda v, f: " / ".join(f.format(u) for u in v)
    built = lambda v: ("not recorded" if all(u is None for u in v)
                       else " / ".join("-" if u is None else f"{u:.1f}" for u in v))
    for s in rows:
        print(f"| {s['seed']} | {s['particles']} ({' + '.join(map(str, s['particles_per_layer']))}) | "
              f"{s['diameter_mm']:.1f}, {s['sample_height_mm']:.1f} | "
              f"{fmt(s['layer_heights_mm'], '{:.1f}')} | {fmt(s['packing_fraction_per_layer'], '{:.3f}')} | "
              f"{s['packing_fraction']:.3f} | {100 * s['max_overlap_ratio']:.2f} % | {s['outside']} | "
              f"{s['coordination_number']:.2f} / {s['coordination_number_force_carrying']:.2f} | "
              f"{fmt(s['course_lift_heights_mm'], '{:.1f}')} | "
              f"{fmt(s['course_packing_fraction_per_lift'], '{:.3f}')} | "
              f"{s['grains_in_lower_course'][-1]} ({s['deepest_grain_below_lower_top_mm'][-1]:.1f}) | "
              f"{built(s['course_heights_as_built_mm'])} | "
              f"{built(s['course_heights_as_built_by_highest_grain_mm'])} | "
              f"{fmt(s['course_heights_by_highest_grain_mm'], '{:.1f}')} | "
              f"{s['highest_grain_top_mm']:.1f}, {s['top_plate_gap_mm']:.1f} | "
              f"{s['packing_fraction_below_highest_grain']:.3f} |")
    if len(rows) > 1:
        mean = lambda k: np.mean([s[k] for s in rows], axis=0)
        print(f"| mean | {mean('particles'):.0f} | | {fmt(mean('layer_heights_mm'), '{:.1f}')} | "
              f"{fmt(mean('packing_fraction_per_layer'), '{:.3f}')} | {mean('packing_fraction'):.3f} | "
              f"{100 * np.max([s['max_overlap_ratio'] for s in rows]):.2f} % (max) | "
              f"{int(np.sum([s['outside'] for s in rows]))} | {mean('coordination_number'):.2f} / "
              f"{mean('coordination_number_force_carrying'):.2f} | "
              f"{fmt(mean('course_lift_heights_mm'), '{:.1f}')} | "
              f"{fmt(mean('course_packing_fraction_per_lift'), '{:.3f}')} | "
              f"{mean('grains_in_lower_course')[-1]:.0f} | | | "
              f"{fmt(mean('course_heights_by_highest_grain_mm'), '{:.1f}')} | "
              f"{mean('highest_grain_top_mm'):.1f}, {mean('top_plate_gap_mm'):.1f} | "
              f"{mean('packing_fraction_below_highest_grain'):.3f} |")
    print("| target (issue 5; paper) | about 5200 | 150, 120 | 60 +- 2 | | 0.57 to 0.61 (0.584 to 0.59) "
          "| < 1 % | 0 | | | | | 60 +- 2 | 60 +- 2 | 60 +- 2 | 120 | |")
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
