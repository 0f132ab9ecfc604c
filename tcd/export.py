"""Snapshots exported to VTK XML files for ParaView, VisIt or PyVista (meshio writes them).

`tcd export FILE.h5 --out DIR` turns every frame of a states file (or the one state of a
prepared sample or checkpoint) into one unstructured-grid file (.vtu) per part and frame, and one
ParaView collection (.pvd) per part that lists the frames with their simulated times, so that
opening `<stem>_particles.pvd` gives a time series:

  particles  one point per sphere (vertex cells). Point data: `radius` and `diameter` (m; scale a
             Glyph filter's spheres by `diameter` with scale factor 1 to draw the true sizes),
             `velocity` (m/s), `speed`, `angular_velocity` (rad/s), `layer`, `id` (the index
             used by contacts and bonds), `sample_index` when a shear renumbered the
             particles (`renumber = true`: the particle's index in its prepared sample), and
             `system` in a batch checkpoint (the samples of
             a batch overlap in space: threshold on it to see one).
  contacts   one line per particle-particle contact, between the two centres (the same points as
             the particles, so contact and particle files overlay). Cell data: `impulse` (N s,
             the impulse on the second particle over the last step, global frame),
             `normal_impulse` (along the line of centres, > 0 in compression),
             `tangential_impulse` (its magnitude), `gap` (m), and, when the time step H is
             known (a states file keeps its scenario), `normal_force` = normal_impulse / H (N):
             colour and scale the tubes by it to see the force chains. Contacts with walls are
             not drawn: their sum is the wall's force.
  bonds      one line per bond. Cell data: `state` (0 intact, 1 broken in tension, 2 broken in
             shear), `intact` (1/0), `impulse`, `normal_impulse`, `tangential_impulse`,
             `normal_force` as for contacts.
  walls      planes as discs (radius `walls/radius`) and cylinders as shells over their axial
             extent, triangulated. Cell data: `wall` (index), `kind` (0 plane, 1 cylinder),
             `force` (N, the force the particles exert on that wall, repeated on each of its
             triangles for colouring: integrating or summing it over cells multiplies it).
             Field data: `wall_force` (N, one row per wall, in wall index order).

A frame at the same time as the next one (the end of a preparation and the start of its shear,
before and after bonding) gets its .vtu files but no entry in the collections, which list one
file per time: the later, the state the run goes on from. A part with nothing in it (no bond
before the bonding, no contact in a first frame) is a valid VTK file with the particles' points
and no cells, which VTK, ParaView and PyVista read; meshio 5.3 cannot read back a .vtu without
cells.

Every file is written atomically (io.atomic_path), the collections last: an interrupted export
leaves complete files only. Nothing is computed that is not in the file except the derived
quantities named above.
"""
from __future__ import annotations

import json
import math
import os
import re
import sys
import tomllib
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from . import io

PARTS = ("particles", "contacts", "bonds", "walls")
WALL_SEGMENTS = 48


# --- reading ---------------------------------------------------------------------------------
def _kind(path) -> str:
    with io._open_tcd(path, None) as f:
        return io._file_kind(f)


def _time_step(scenario_text: str) -> float | None:
    """H of the scenario stored in a states file (the config default when [solver] omits it);
    None when there is no scenario text or it does not parse."""
    if not scenario_text:
        return None
    try:
        solver = tomllib.loads(scenario_text).get("solver", {})
    except tomllib.TOMLDecodeError:
        return None
    if "time_step" in solver:
        return float(solver["time_step"])
    from .config import SolverConfig
    return float(SolverConfig.model_fields["time_step"].default)


#: a states file's attribute that records the time step of its frames where a branch (`tcd run
#: --from`) changed it: JSON [[first frame, H], ...], each H from its frame on
TIME_STEPS_ATTR = "time_steps"


def frame_time_steps(f, count: int) -> list:
    """H of each of the `count` frames of the open states file `f` (None where unknown): the
    `time_steps` a branch recorded, else its scenario's one time step for every frame."""
    steps = [_time_step(io._attr_text(f, "scenario"))] * count
    if TIME_STEPS_ATTR not in f.attrs:
        return steps
    try:
        segments = json.loads(io._attr_text(f, TIME_STEPS_ATTR))
        segments = sorted((int(k), float(h)) for k, h in segments)
    except (ValueError, TypeError):
        raise ValueError(f"{f.filename}: its {TIME_STEPS_ATTR} attribute is not readable "
                         "(expected [[first frame, time step], ...])") from None
    if any(not (h > 0 and math.isfinite(h)) or k < 0 for k, h in segments):
        raise ValueError(f"{f.filename}: its {TIME_STEPS_ATTR} attribute holds a time step that "
                         "is not a positive number, or a negative frame")
    for k, h in segments:
        steps[k:] = [h] * max(count - k, 0)
    return steps


def refuse_batch(state: dict, path, command: str) -> None:
    """ValueError when `state` (load_states) holds several samples batched side by side in one
    simulation (a `tcd run --batch` checkpoint: particles/system): drawn or reduced as one,
    they would give one picture or row of samples inside each other. `tcd export` keeps them
    apart (each grain's `system`)."""
    system = state.get("particles/system")
    if system is not None and np.asarray(system).size and len(np.unique(system)) > 1:
        raise ValueError(f"{path}: a batch checkpoint, {len(np.unique(system))} samples side by "
                         f"side in one simulation (particles/system): {command} reads one "
                         "sample; give a sample's own files (sample_<seed>/states.h5 or "
                         "prepared.h5), or `tcd export` it (each grain keeps its system)")


def load_states(path, frames="all") -> tuple[list[dict], float | None]:
    """The frames to export (flat dicts as io.read_frame gives them) and the time step H their
    impulses were computed with (None if unknown, or if the frames' differ: each frame where
    known holds its own as "time_step"). A checkpoint or prepared sample gives its single state
    as frame 0."""
    path = os.fspath(path)
    kind = _kind(path)
    if kind == io.FILE_STATES:
        count = io.frame_count(path)
        if isinstance(frames, str):
            if frames != "all":
                raise ValueError(f"frames={frames!r}: expected 'all' or a list of frame indices")
            indices = list(range(count))
        else:
            indices = []
            for k in frames:
                kk = int(k) + count if int(k) < 0 else int(k)
                if not 0 <= kk < count:
                    raise ValueError(f"{path}: frame index {k} out of range ({count} frames)")
                if kk not in indices:           # -1 and count - 1 are one frame
                    indices.append(kk)
        import h5py
        with h5py.File(path, "r") as f:
            # each frame's own: a run that went on from another at another time step
            # (`tcd run --from`) holds frames of both (session 72's review: the earlier frames'
            # forces came out scaled by H_old / H_new)
            steps = frame_time_steps(f, count)
        out, diverged = [], []
        for k in indices:
            frame = io.read_frame(path, k)
            # a diverged run's frames are still worth looking at: kept, and named
            io.check_state(frame, f"{path}: frame {k}", finite_positions=False)
            if not np.all(np.isfinite(frame["particles/x"])):
                diverged.append(k)
            frame["index"] = k
            if steps[k] is not None:
                frame["time_step"] = steps[k]
            out.append(frame)
        if diverged:
            shown = ", ".join(map(str, diverged[:5])) + (" ..." if len(diverged) > 5 else "")
            print(f"tcd: warning: {path}: {len(diverged)} frame(s) hold positions that are not "
                  f"finite (a run that diverged?): {shown}", file=sys.stderr)
        return out, _common_time_step(out)
    if kind == io.FILE_CHECKPOINT:
        if not (isinstance(frames, str) and frames == "all") and (
                not list(frames) or any(int(k) not in (0, -1) for k in frames)):
            raise ValueError(f"{path}: a checkpoint holds one state (frame 0), got frames {frames}")
        arrays, meta = io.load_checkpoint(path)
        frame = {k: v for k, v in arrays.items() if k.split("/")[0] in io.GROUP_SIZE_SYMBOL}
        if "particles/x" not in frame:
            raise ValueError(f"{path}: checkpoint without particles/x")
        # a checkpoint's contact list may hold unused capacity past its `start` table's end
        if "contacts/start" in frame and "contacts/i" in frame:
            m = int(frame["contacts/start"][-1])
            for key in [k for k in frame if k.startswith("contacts/")]:
                if key != "contacts/start":
                    frame[key] = frame[key][:m]
        io.check_state(frame, path, wall_slots=io.meta_wall_slots(frame, meta),
                       finite_positions=False)
        if not np.all(np.isfinite(frame["particles/x"])):
            print(f"tcd: warning: {path}: its state holds positions that are not finite (a run "
                  "that diverged?)", file=sys.stderr)
        try:
            frame.update(time=float(meta.get("time", 0.0)), step=int(meta.get("step", 0)),
                         stage=str(meta.get("stage", "")), index=0)
        except (AttributeError, TypeError, ValueError):
            raise ValueError(f"{path}: its meta's time, step or stage is not readable") from None
        # a run's checkpoint or prepared sample keeps its scenario, and with it the step its
        # impulses were computed with (session 72: it was taken as unknown)
        text = meta.get("scenario_text")
        h = _time_step(text) if isinstance(text, str) else None
        if h is not None:
            frame["time_step"] = h
        return [frame], h
    raise ValueError(f"{path}: a tcd {kind} file holds no particle states (expected a states "
                     f"file, a prepared sample or a checkpoint)")


def _common_time_step(frames: list) -> float | None:
    """The time step of every frame in `frames` when they share one (None when one is unknown
    or they differ: each frame's own is its "time_step")."""
    steps = {frame.get("time_step") for frame in frames}
    return steps.pop() if len(steps) == 1 else None


# --- meshes ----------------------------------------------------------------------------------
def _pair_data(frame, group, h):
    """Line cells between particle centres and their cell data, for `group` (contacts or bonds):
    pairs whose j is a wall are dropped."""
    x = np.asarray(frame["particles/x"])
    n = len(x)
    i = np.asarray(frame.get(f"{group}/i", np.zeros(0, np.int32)), dtype=np.int64)
    j = np.asarray(frame.get(f"{group}/j", np.zeros(0, np.int32)), dtype=np.int64)
    # bonds join particles; a contact's j may also be a wall (j - N)
    walls = len(frame["walls/kind"]) if "walls/kind" in frame else np.iinfo(np.int32).max
    limit = n if group == "bonds" else n + walls
    if len(i) and (i.min() < 0 or i.max() >= n or j.min() < 0 or j.max() >= limit):
        raise ValueError(f"{group}/i or {group}/j refer to bodies that do not exist "
                         f"({n} particles, {0 if group == 'bonds' else walls} walls)")
    keep = j < n
    i, j = i[keep], j[keep]
    imp = np.asarray(frame.get(f"{group}/impulse", np.zeros((len(keep), 3))))[keep]
    d = x[j] - x[i]
    length = np.linalg.norm(d, axis=1)
    normal = d / np.where(length > 0, length, 1.0)[:, None]
    rn = np.einsum("ij,ij->i", imp, normal)
    rt = np.linalg.norm(imp - rn[:, None] * normal, axis=1)
    data = {"impulse": imp, "normal_impulse": rn, "tangential_impulse": rt}
    if group == "contacts":
        if "contacts/gap" in frame:
            data["gap"] = np.asarray(frame["contacts/gap"])[keep]
    else:
        state = np.asarray(frame.get("bonds/state", np.zeros(len(keep), np.int8)))[keep]
        data["state"] = state.astype(np.int32)
        data["intact"] = (state == io.BOND_INTACT).astype(np.int32)
    if h is not None:
        data["normal_force"] = rn / h
    return np.stack([i, j], axis=1), data


def _wall_mesh(frame):
    """Triangles of every wall (disc or cylinder shell) with per-cell wall index, kind, force."""
    kinds = np.asarray(frame.get("walls/kind", np.zeros(0, np.int32)))
    forces = _wall_forces(frame)
    pts, tris, wall, kind, force = [], [], [], [], []
    base = 0
    phi = np.linspace(0.0, 2.0 * math.pi, WALL_SEGMENTS, endpoint=False)
    for w in range(len(kinds)):
        p = np.asarray(frame["walls/point"][w], dtype=float)
        a = np.asarray(frame["walls/direction"][w], dtype=float)
        a = a / np.linalg.norm(a)
        r = float(frame["walls/radius"][w])
        # two unit vectors across the axis
        helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = np.cross(a, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        ring = r * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
        s = WALL_SEGMENTS
        if kinds[w] == io.WALL_CYLINDER:
            lo, hi = (float(v) for v in frame["walls/extent"][w])
            pts += [p + lo * a + ring, p + hi * a + ring]
            k = np.arange(s)
            k1 = (k + 1) % s
            cells = np.concatenate([np.stack([k, k1, s + k1], 1), np.stack([k, s + k1, s + k], 1)])
            count = 2 * s
        else:
            pts += [p[None, :], p + ring]
            k = np.arange(s)
            cells = np.stack([np.zeros(s, int), 1 + k, 1 + (k + 1) % s], 1)
            count = s
        tris.append(cells + base)
        base += sum(len(q) for q in pts[-2:])
        wall += [w] * count
        kind += [int(kinds[w])] * count
        force += [forces[w]] * count
    if not tris:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), {}
    data = {"wall": np.asarray(wall, np.int32), "kind": np.asarray(kind, np.int32),
            "force": np.asarray(force)}
    return np.concatenate(pts), np.concatenate(tris).astype(np.int64), data


def _mesh(frame, part, h):
    import meshio
    x = np.asarray(frame["particles/x"])
    n = len(x)
    if part == "particles":
        v = np.asarray(frame.get("particles/v", np.zeros_like(x)))
        r = np.asarray(frame["particles/radius"])         # (required: io.check_state)
        data = {"radius": r, "diameter": 2.0 * r, "velocity": v,
                "speed": np.linalg.norm(v, axis=1),
                "angular_velocity": np.asarray(frame.get("particles/w", np.zeros_like(x))),
                "layer": np.asarray(frame.get("particles/layer", np.zeros(n, np.int32)), np.int32),
                "id": np.arange(n, dtype=np.int64)}
        if "particles/sample_index" in frame:    # a renumbered shear
            data["sample_index"] = np.asarray(frame["particles/sample_index"], np.int32)
        if "particles/system" in frame:     # a batch checkpoint: samples side by side
            data["system"] = np.asarray(frame["particles/system"], np.int32)
        return meshio.Mesh(x, [("vertex", np.arange(n, dtype=np.int64)[:, None])],
                           point_data=data)
    if part in ("contacts", "bonds"):
        lines, data = _pair_data(frame, part, h)
        return meshio.Mesh(x, [("line", lines)], cell_data={k: [v] for k, v in data.items()})
    points, tris, data = _wall_mesh(frame)
    return meshio.Mesh(points, [("triangle", tris)], cell_data={k: [v] for k, v in data.items()})


def _wall_forces(frame) -> np.ndarray:
    """Each wall's force (N), one row per wall: the walls file's field data `wall_force`."""
    if "walls/force" in frame:
        return np.asarray(frame["walls/force"], dtype=float).reshape(-1, 3)
    return np.zeros((len(frame.get("walls/kind", ())), 3))


# --- writing ---------------------------------------------------------------------------------
def _add_field_data(path, name: str, values: np.ndarray) -> None:
    """Put `values` (rows of 3) into the .vtu at `path` as FieldData `name` (meshio 5.3 writes
    no field data to a .vtu; VTK, ParaView, PyVista and meshio's reader read it). The numbers
    in ASCII, each as Python's repr: the same doubles when read back."""
    text = Path(path).read_text()
    head = "<UnstructuredGrid>\n"
    if head not in text:
        raise ValueError(f"{path}: no <UnstructuredGrid> element to add field data to")
    numbers = " ".join(repr(float(v)) for v in np.asarray(values, float).ravel())
    block = (f'<FieldData>\n<DataArray type="Float64" Name="{name}" '
             f'NumberOfTuples="{len(values)}" NumberOfComponents="3" format="ascii">\n'
             f'{numbers}\n</DataArray>\n</FieldData>\n')
    Path(path).write_text(text.replace(head, head + block, 1))


def _one_per_time(entries) -> list:
    """The collection's (time, file) entries with one file per time: of frames at the same
    time (the end of a preparation and the start of its shear, before and after bonding) the
    last, which is the state the run goes on from. A reader of a .pvd (ParaView, PyVista)
    shows one dataset per time, the first listed, so listing both hid the bonded one."""
    kept = []
    for t, name in entries:
        if kept and kept[-1][0] == t:
            kept[-1] = (t, name)
        else:
            kept.append((t, name))
    return kept


#: the comment of a .pvd that names the file it was exported from (a JSON string: its "--"
#: written as "-\u002d", which an XML comment cannot hold)
_SOURCE_COMMENT = re.compile(r'<!-- tcd export source: ("(?:[^"\\]|\\.)*") -->')


def _pvd(entries, source: str | None = None) -> str:
    rows = "\n".join(f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(name)}/>'
                     for t, name in _one_per_time(entries))
    mark = ("" if source is None else "<!-- tcd export source: "
            + json.dumps(source).replace("--", "-\\u002d") + " -->\n")
    return ('<?xml version="1.0"?>\n' + mark
            + '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
            f'  <Collection>\n{rows}\n  </Collection>\n</VTKFile>\n')


def exported_from(pvd) -> str | None:
    """The file the .pvd at `pvd` was exported from (None: not said, or not readable)."""
    try:
        with open(pvd, encoding="utf-8") as fh:
            head = fh.read(8192)
    except (OSError, UnicodeDecodeError):
        return None
    found = _SOURCE_COMMENT.search(head)
    if not found:
        return None
    try:
        return json.loads(found.group(1))
    except ValueError:
        return None


def export(path, out_dir, *, frames="all", parts=PARTS, prefix: str | None = None) -> list[Path]:
    """Write the VTK files of `frames` of `path` into `out_dir` (created); return their paths,
    collections last. `parts`: any of particles, contacts, bonds, walls."""
    import meshio
    parts = tuple(parts)
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts:
        raise ValueError(f"parts {', '.join(unknown) or '(none)'}: expected some of "
                         f"{', '.join(PARTS)}")
    states, h = load_states(path, frames)
    if not states:
        raise ValueError(f"{path}: no frames to export")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"{out_dir}: exists and is not a directory")
    if prefix is not None and (not prefix or prefix != Path(prefix).name or prefix in (".", "..")):
        raise ValueError(f"--prefix {prefix!r}: expected a file name prefix (no folder)")
    stem = prefix or Path(path).stem
    source = os.path.realpath(os.fspath(path))
    # the targets are checked before anything is written: a folder where a file goes, and
    # the export of another file of the same name (every sample's is states.h5) that this
    # one would overwrite frame by frame and mix with its own (session 72's review)
    names = [f"{stem}_{part}_{frame['index']:06d}.vtu" for frame in states for part in parts]
    names += [f"{stem}_{part}.pvd" for part in parts]
    for name in names:
        if (out_dir / name).is_dir():
            raise ValueError(f"{out_dir / name}: is a directory, not a file; nothing was "
                             "written")
    for part in parts:
        earlier = exported_from(out_dir / f"{stem}_{part}.pvd")
        if earlier is not None and earlier != source:
            raise ValueError(f"{out_dir}: holds an export of {earlier} ({stem}_{part}.pvd), "
                             f"which this export of {path} would overwrite and mix with its "
                             "own frames; export into another folder, or give --prefix NAME")
    written, collections = [], {p: [] for p in parts}
    # every mesh is made before the first file is written: a frame that lacks what a part
    # needs (a damaged file) stops the export with nothing written, not half of it
    meshes = [(frame, part, _mesh(frame, part, frame.get("time_step", h)))
              for frame in states for part in parts]
    out_dir.mkdir(parents=True, exist_ok=True)
    for frame, part, mesh in meshes:
        name = f"{stem}_{part}_{frame['index']:06d}.vtu"
        with io.atomic_path(out_dir / name) as tmp:
            meshio.write(tmp, mesh, file_format="vtu")
            if part == "walls":
                _add_field_data(tmp, "wall_force", _wall_forces(frame))
        written.append(out_dir / name)
        collections[part].append((float(frame["time"]), name))
    for part, entries in collections.items():
        target = out_dir / f"{stem}_{part}.pvd"
        with io.atomic_path(target) as tmp:
            Path(tmp).write_text(_pvd(entries, source), encoding="utf-8")
        written.append(target)
    return written
