"""Micromechanics of the snapshots: contact network, fabric and mean stress in the grains.

`tcd analyse FILE.h5 --out PREFIX` reads every frame of a states file (or the one state of a
prepared sample or checkpoint; see export.load_states) and writes one row per frame to
PREFIX.h5 (a tcd series file, units on every dataset) and PREFIX.csv:

  particles, contacts (particle pairs listed as contacts, within the alert distance: touching
      or nearly; a pair that also holds an intact bond counts as a bond only, as the solver
      takes it), wall_contacts, bonds_intact, bonds_broken
  coordination_contacts = 2 contacts / particles;
  coordination_contacts_force_carrying = the same over the contacts that pressed their grains
  together over the last step (observables.carries_force);
  coordination_bonds = 2 bonds_intact / particles
  normal_force_mean, normal_force_max (N): over the particle contacts in compression
      (R.n > 0; n along the line of centres), force = impulse / H
  stress_xx ... stress_xy (Pa): mean stress inside the grains, Love-Weber
      sigma = 1 / sum(V_p) * sum_p sum_c (x_c - x_p) (x) f_c,
      with the contacts and the intact bonds. For a pair (i, j) with impulse R on j over the
      step, both grains together give -(x_j - x_i) (x) R / H wherever the contact point lies on
      the line of centres; a wall contact gives r_i n (x) (-R / H), n from the grain's centre to
      the wall. Tension is positive: a confined sample has negative diagonal terms. Multiply by
      the packing fraction for the stress over the sample's volume. The symmetric part is
      written (the antisymmetric part is the unbalanced torque, zero at equilibrium).
  fabric_xx ... fabric_xy (1): (1 / M) sum n (x) n over the M particle pairs listed as
      contacts or bonded, each pair once (trace 1; 1/3 on the diagonal for an isotropic
      network), and fabric_anisotropy, its largest minus its smallest eigenvalue.

Forces need the time step H, which a states file gives through its scenario; for a checkpoint
(no scenario) give it with `--time-step` (otherwise the force and stress columns are left out).
"""
from __future__ import annotations

import math
import os
import sys

import numpy as np

from . import io
from . import observables as obs
from .export import load_states

COMPONENTS = (("xx", 0, 0), ("yy", 1, 1), ("zz", 2, 2), ("yz", 1, 2), ("xz", 0, 2), ("xy", 0, 1))


def _pairs(frame, group):
    """(i, j, R) of `group`, pairs between two particles only (bonds: intact ones only)."""
    n = len(frame["particles/x"])
    i = np.asarray(frame.get(f"{group}/i", np.zeros(0, np.int32)), dtype=np.int64)
    j = np.asarray(frame.get(f"{group}/j", np.zeros(0, np.int32)), dtype=np.int64)
    imp = np.asarray(frame.get(f"{group}/impulse", np.zeros((len(i), 3))), dtype=float)
    keep = j < n
    if group == "bonds":
        keep &= np.asarray(frame.get("bonds/state", np.zeros(len(i), np.int8))) == io.BOND_INTACT
    return i[keep], j[keep], imp[keep]


def _unbonded_contacts(frame):
    """`_pairs(frame, "contacts")` less the pairs that also hold an intact bond: in the frame
    written as the bonds are made the contact list still has every pair just bonded (the
    solver takes a bonded pair as its bond from the next step), so each pair counts once."""
    ci, cj, cimp = _pairs(frame, "contacts")
    bi, bj, _ = _pairs(frame, "bonds")
    if not len(bi) or not len(ci):
        return ci, cj, cimp
    n = len(frame["particles/x"])
    key = np.minimum(ci, cj) * n + np.maximum(ci, cj)
    keep = ~np.isin(key, np.minimum(bi, bj) * n + np.maximum(bi, bj))
    return ci[keep], cj[keep], cimp[keep]


def wall_normals(frame, i, w):
    """Unit vectors from grain i's centre toward wall w (plane: against its normal; cylinder:
    radially outward from its axis)."""
    x = np.asarray(frame["particles/x"], dtype=float)[i]
    kind = np.asarray(frame["walls/kind"])[w]
    point = np.asarray(frame["walls/point"], dtype=float)[w]
    d = np.asarray(frame["walls/direction"], dtype=float)[w]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    rel = x - point
    radial = rel - np.einsum("ij,ij->i", rel, d)[:, None] * d
    length = np.linalg.norm(radial, axis=1, keepdims=True)
    radial = radial / np.where(length > 0, length, 1.0)
    return np.where((kind == io.WALL_CYLINDER)[:, None], radial, -d)


def grain_stress(frame, h: float) -> np.ndarray:
    """Mean stress tensor inside the grains (Pa, 3x3, not symmetrised), Love-Weber."""
    x = np.asarray(frame["particles/x"], dtype=float)
    r = np.asarray(frame["particles/radius"], dtype=float)
    n = len(x)
    s = np.zeros((3, 3))
    for group in ("contacts", "bonds"):
        i, j, imp = _pairs(frame, group)
        s -= np.einsum("ki,kj->ij", x[j] - x[i], imp)
    i = np.asarray(frame.get("contacts/i", np.zeros(0, np.int32)), dtype=np.int64)
    j = np.asarray(frame.get("contacts/j", np.zeros(0, np.int32)), dtype=np.int64)
    on_wall = j >= n
    if np.any(on_wall):
        iw, w = i[on_wall], j[on_wall] - n
        imp = np.asarray(frame["contacts/impulse"], dtype=float)[on_wall]
        lever = r[iw, None] * wall_normals(frame, iw, w)
        s -= np.einsum("ki,kj->ij", lever, imp)
    return s / (h * float(np.sum(4.0 / 3.0 * math.pi * r**3)))


def fabric(frame, pairs=None) -> np.ndarray:
    """(1 / M) sum n (x) n over the M particle pairs listed as contacts (within the alert
    distance: touching or nearly) or bonded, each pair once (3x3, trace 1; zeros when there
    is none). `pairs`: the frame's (_unbonded_contacts, intact bonds) when the caller has
    them."""
    x = np.asarray(frame["particles/x"], dtype=float)
    if pairs is None:
        pairs = (_unbonded_contacts(frame), _pairs(frame, "bonds"))
    branches = []
    for i, j, _ in pairs:
        branches.append(x[j] - x[i])
    b = np.concatenate(branches)
    length = np.linalg.norm(b, axis=1)
    b = b[length > 0] / length[length > 0, None]
    if not len(b):
        return np.zeros((3, 3))
    return np.einsum("ki,kj->ij", b, b) / len(b)


def frame_row(frame, h: float | None) -> dict:
    x = np.asarray(frame["particles/x"], dtype=float)
    n = len(x)
    contacts, bonds = _unbonded_contacts(frame), _pairs(frame, "bonds")
    ci, cj, cimp = contacts
    bi = bonds[0]
    state = np.asarray(frame.get("bonds/state", np.zeros(0, np.int8)))
    wall_contacts = int(np.count_nonzero(np.asarray(frame.get("contacts/j", [])) >= n))
    row = {"time": float(frame["time"]), "step": int(frame["step"]), "particles": n,
           "contacts": len(ci), "wall_contacts": wall_contacts, "bonds_intact": len(bi),
           "bonds_broken": int(np.count_nonzero(state != io.BOND_INTACT)),
           "coordination_contacts": 2.0 * len(ci) / n if n else 0.0,
           "coordination_contacts_force_carrying": obs.coordination_number(
               ci, cj, n, obs.carries_force(ci, cj, cimp, x)),
           "coordination_bonds": 2.0 * len(bi) / n if n else 0.0}
    if h is not None:
        d = x[cj] - x[ci]
        length = np.linalg.norm(d, axis=1)
        rn = np.einsum("ij,ij->i", cimp, d / np.where(length > 0, length, 1.0)[:, None]) / h
        pressed = rn[rn > 0]
        row["normal_force_mean"] = float(pressed.mean()) if len(pressed) else 0.0
        row["normal_force_max"] = float(pressed.max()) if len(pressed) else 0.0
        s = grain_stress(frame, h)
        s = 0.5 * (s + s.T)
        for name, a, b in COMPONENTS:
            row[f"stress_{name}"] = float(s[a, b])
    f = fabric(frame, (contacts, bonds))
    for name, a, b in COMPONENTS:
        row[f"fabric_{name}"] = float(f[a, b])
    eig = np.linalg.eigvalsh(f)
    row["fabric_anisotropy"] = float(eig[-1] - eig[0])
    return row


UNITS = {"time": "s", "normal_force_mean": "N", "normal_force_max": "N",
         **{f"stress_{name}": "Pa" for name, _, _ in COMPONENTS}}


def _is_analysis(path) -> bool:
    """Whether the HDF5 file at `path` is an output of `analyse` (its root attributes; files
    written before session 42 lack `analysis` but have `source` and `stages`)."""
    import h5py
    try:
        with h5py.File(path, "r") as f:
            return "analysis" in f.attrs or ("source" in f.attrs and "stages" in f.attrs)
    except OSError:
        return False


def analyse(path, out_prefix, *, frames="all", time_step: float | None = None) -> list[str]:
    """Write PREFIX.h5 and PREFIX.csv (one row per frame); return their paths."""
    if time_step is not None and not (time_step > 0 and math.isfinite(time_step)):
        raise ValueError(f"time step {time_step!r}: expected a positive number of seconds")
    prefix = os.fspath(out_prefix)
    for suffix in (".h5", ".csv"):              # PREFIX.h5 given for PREFIX: no PREFIX.h5.h5
        if prefix.endswith(suffix):
            prefix = prefix[: -len(suffix)]
    directory = os.path.dirname(os.path.abspath(prefix))
    if not os.path.isdir(directory):
        what = "is a file, not a folder" if os.path.exists(directory) else "does not exist"
        raise ValueError(f"{prefix}: directory {directory} {what}")
    if not os.path.basename(prefix):
        raise ValueError(f"--out {out_prefix!r}: give a file name prefix (PREFIX.h5 and "
                         "PREFIX.csv are written)")
    h5, csv = prefix + ".h5", prefix + ".csv"
    source = os.path.realpath(os.fspath(path))
    for target in (h5, csv):
        if os.path.realpath(target) == source:
            raise ValueError(f"--out {out_prefix}: would overwrite the file being analysed "
                             f"({path}); choose another prefix")
    # an earlier analysis is replaced; any other file (a run's shear_series.h5 and .csv) is not
    for target in (h5, csv):
        if os.path.isdir(target):
            raise ValueError(f"--out {out_prefix}: {target} is a directory; choose another "
                             "prefix, or remove it")
    if os.path.exists(h5) and not _is_analysis(h5) or os.path.exists(csv) and not os.path.exists(h5):
        raise ValueError(f"--out {out_prefix}: {h5 if os.path.exists(h5) else csv} exists and "
                         "is not an output of tcd analyse (a run's series?); choose another "
                         "prefix, or remove it")
    states, h = load_states(path, frames)
    if not states:
        raise ValueError(f"{path}: no frames to analyse")
    # each frame's own time step where the file records it (a run that went on from another
    # at another step holds frames of both)
    own = sorted({frame["time_step"] for frame in states if "time_step" in frame})
    if time_step is not None:
        if own and not all(math.isclose(float(time_step), x, rel_tol=1e-12) for x in own):
            shown = " and ".join(f"{x:g}" for x in own)
            raise ValueError(f"--time-step {time_step:g}: {path} records its own time step, "
                             f"{shown} s, with which its impulses were computed; leave "
                             "--time-step out")
        for frame in states:
            frame.setdefault("time_step", float(time_step))
        h = float(time_step)
    from .export import refuse_batch
    for state in states:
        refuse_batch(state, path, "tcd analyse")
    if not own and time_step is None:
        print(f"tcd analyse: {path} does not give the time step (it records no scenario): "
              "normal forces and stresses are left out; pass --time-step H to have them",
              file=sys.stderr)
    steps = [frame.get("time_step") for frame in states]
    rows = [frame_row(frame, frame.get("time_step")) for frame in states]
    series = {key: np.asarray([row[key] for row in rows]) for key in rows[0]}
    series["frame"] = np.asarray([frame["index"] for frame in states], np.int64)
    keys = ["frame"] + list(rows[0])
    series = {k: series[k] for k in keys}
    io.write_series(h5, series, units=UNITS, csv_path=csv,
                    attrs={"analysis": "tcd analyse", "source": os.fspath(path),
                           "time_step": (h if h is not None else "unknown")
                           if len(set(steps)) == 1 else
                           [x if x is not None else float("nan") for x in steps],
                           "stages": [str(frame["stage"]) for frame in states]})
    return [h5, csv]
