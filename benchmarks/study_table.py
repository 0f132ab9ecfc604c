"""The README's table of a shear study: one Markdown row per sample of a finished run directory
(its `summary.json`), then the mean and population standard deviation, the paper's simulations,
the experiments and the relative errors of the mean (those three only for the paper's Leutner
test: a summary whose `paper_test` is false gets a line saying how its test differs). Nothing is recomputed by a simulation.

    python benchmarks/study_table.py runs/leutner_shear
    python benchmarks/study_table.py runs/seeds1-3 runs/seeds4-5    # one study split by --seeds

Several run directories (the parts of one study, `tcd run --seeds`) are merged as `tcd figures`
merges them: each seed once, the same scenario, the mean and std over all their samples.

Columns: seed, particles, peak stress and its displacement (smoothed curve, the run's window;
"(end)" where the curve still rose at its end, `peak_at_end`, so the "peak" is no failure),
residual stress at the end, bonds broken (tension + shear) of all bonds, the share of the broken
bonds within a quarter ring height of the shear plane (next to that band's share of all bonds),
the mean displacement of the upper and lower grains over the ring's travel, the largest kinetic
energy over the work of the moving walls, and the wall time of the shear.
"""
import argparse
import json
import pathlib


def _shear(sample: dict) -> dict:
    return next(v for k, v in sample["stages"].items() if k.endswith(":shear"))


def rows_of(summary: dict) -> list[list[str]]:
    rows = []
    for sample in summary["samples"]:
        sh = _shear(sample)
        rows.append([
            str(sample["seed"]), str(sh["particles"]),
            f"{sh['tau_peak_MPa']:.3f}",
            f"{sh['d_peak_mm']:.2f}" + (" (end)" if sh.get("peak_at_end") is True else ""),
            f"{sh['residual_MPa']:.3f}",
            f"{sh['bonds_broken']} ({sh['bonds_broken_tension']} + {sh['bonds_broken_shear']}) / {sh['bonds_total']}",
            f"{sh['broken_near_plane_fraction']:.2f} ({sh['bonds_near_plane_fraction']:.2f})",
            f"{sh['upper_mean_dx_over_ring']:.2f} / {sh['lower_mean_dx_over_ring']:.2f}",
            f"{sh['kinetic_over_work_max']:.1e}", f"{sh['wall_time_s']:.0f}",
        ])
    mean, std = summary["mean"], summary["std"]
    if len(summary["samples"]) > 1:
        rows.append(["mean ± std", "", f"{mean['tau_peak_MPa']:.3f} ± {std['tau_peak_MPa']:.3f}",
                     f"{mean['d_peak_mm']:.2f} ± {std['d_peak_mm']:.2f}",
                     f"{mean['residual_MPa']:.3f} ± {std['residual_MPa']:.3f}", "", "", "", "", ""])
    if summary.get("paper_test") is False:      # another test: not compared with the paper's
        return rows
    paper, exp, rel = summary["paper_simulation"], summary["experiment"], summary["relative_error"]
    rows.append(["paper's simulations (LMGC90)", "about 5200", f"{paper['tau_peak_MPa']:.3f}",
                 f"{paper['d_peak_mm']:.2f}", "", "", "", "", "", ""])
    rows.append(["experiments (5 cores)", "", f"{exp['tau_peak_MPa']:.3f}", f"{exp['d_peak_mm']:.2f}",
                 "", "", "", "", "", ""])
    label = "mean vs experiments" if len(summary["samples"]) > 1 else "vs experiments"
    rows.append([label, "", f"{100 * rel['tau_peak']:+.1f} %", f"{100 * rel['d_peak']:+.1f} %",
                 "", "", "", "", "", ""])
    return rows


HEAD = ["seed", "particles", "peak τ (MPa)", "at d (mm)", "τ at 2.5 mm (MPa)",
        "bonds broken (tension + shear) / all", "broken near the plane (all bonds there)",
        "upper / lower grains' travel over the ring's", "max kinetic energy / wall work",
        "shear wall time (s)"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", nargs="+", help="a finished run directory (with summary.json); "
                    "several: the parts of one study")
    args = ap.parse_args(argv)
    parts = []
    for run in map(pathlib.Path, args.run):
        path = run / "summary.json"
        if not path.exists():
            ap.error(f"{run}: no summary.json (is the run finished?)")
        parts.append((run, json.loads(path.read_text())))
    if len(parts) == 1:
        summary = parts[0][1]
    else:
        from tcd.figures import check_one_study, merge_summaries
        try:
            check_one_study([run for run, _ in parts])
            summary = merge_summaries(parts)
        except ValueError as exc:
            ap.error(str(exc))
    print("| " + " | ".join(HEAD) + " |")
    print("|" + "---|" * len(HEAD))
    for row in rows_of(summary):
        print("| " + " | ".join(row) + " |")
    if summary.get("paper_test") is False:
        from tcd.figures import not_compared_note
        print(f"\n{not_compared_note(summary)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
