"""HDF5 states, time series and checkpoints, written crash-safe (NumPy and h5py only, no Taichi).

Every file tcd writes is replaced atomically: the new content goes to a temporary file in the
same directory (``.<name>.<random>.tmp``), which is flushed, fsync'ed and then ``os.replace``d
over the target; the directory is fsync'ed afterwards. HDF5 files are built in memory and written
to the temporary file in one write (``hdf5_writer``; files larger than ``IN_MEMORY_BYTES`` are
written by HDF5 on the disk); appending a frame reads the existing file in and appends there.
Invariant: whatever interrupts a write (an exception, Ctrl-C, SIGKILL, a full disk), the target
path holds either the complete previous file or the complete new one, never a mix. An exception
removes the temporary file; a SIGKILL may leave one behind (``.*.tmp``), which is harmless and
may be deleted. The cost of this guarantee is that an append rewrites the whole file, so states
files are meant for snapshots, not every step.
There is one writer per file; two processes appending to the same file concurrently lose frames.

Schema version 1
----------------
Every HDF5 file has the root attributes ``schema_version`` (= 1), ``tcd_file`` (``"states"``,
``"series"`` or ``"checkpoint"``), ``tcd_version`` and ``created`` (ISO 8601, UTC). Every dataset
of a states or series file has a ``units`` attribute (SI: "m", "m/s", "rad/s", "N", "N s", "s";
"1" for dimensionless numbers, indices and codes).

``states.h5`` (snapshots of the granular sample)
    root attributes: as above, plus ``scenario`` (the scenario TOML text).
    ``frames/000000``, ``frames/000001``, ...: one group per snapshot, named by its 0-based index
    in 6 digits (more digits past 999999), with attributes ``time`` (s, float), ``time_units``
    ("s"), ``step`` (int) and ``stage`` (str), holding the datasets

    ========================  ======  =======  ====================================================
    dataset                   shape   units    meaning
    ========================  ======  =======  ====================================================
    particles/x               (N,3)   m        centre positions (required in every frame)
    particles/v               (N,3)   m/s      translational velocities
    particles/w               (N,3)   rad/s    angular velocities
    particles/radius          (N,)    m        radii
    particles/layer           (N,)    1        int32, compaction layer the particle was poured in
    particles/sample_index    (N,)    1        int32, the particle's index in its sample, present
                                               when a stage renumbered the particles (a shear
                                               with ``renumber = true``); absent: the index
    walls/kind                (W,)    1        int32, 0 plane, 1 cylinder shell
    walls/point               (W,3)   m        point on the plane / on the cylinder axis
    walls/direction           (W,3)   1        unit normal into the sample / unit cylinder axis
    walls/radius              (W,)    m        cylinder inner radius / plane plate size (drawing)
    walls/extent              (W,2)   m        cylinder axial range (lo, hi) relative to point
    walls/force               (W,3)   N        force the particles exert on the wall
    contacts/i, contacts/j    (M,)    1        int32 body indices; j >= N means wall j - N
    contacts/impulse          (M,3)   N s      impulse on body j over the last step (global)
    contacts/gap              (M,)    m        signed gap (negative: interpenetration)
    bonds/i, bonds/j          (B,)    1        int32 particle indices
    bonds/state               (B,)    1        int8, 0 intact, 1 broken in tension, 2 in shear
    bonds/impulse             (B,3)   N s      bond impulse over the last step (global)
    bonds/broken_time         (B,)    s        time of breakage, NaN while intact
    bonds/broken_position     (B,3)   m        position of breakage (NaN while intact)
    ========================  ======  =======  ====================================================

    A frame is passed as a flat dict keyed by these paths. Any group is optional except
    ``particles/x``. Extra keys are stored as datasets too (``"bonds/history_n"``,
    ``"diagnostics/residual"``); inside the four groups above their first axis must have the
    group's length (N, W, M or B). Units of extra keys come from the ``units`` argument, "1" by
    default. Real-valued schema fields keep their floating dtype (float32 or float64, stored and
    read back bit-exact); integer schema fields are stored with the dtype given above, converted
    from any integer dtype whose values fit.

``series.h5`` (time series of observables)
    root attributes: as above, plus any ``attrs`` given to :func:`write_series` (strings, numbers
    and numeric arrays as they are, other values as JSON text). One dataset per key, all with the
    same first-axis length, each with ``units``. An optional CSV twin has a header row
    ``time [s],force_top [N],...`` and one row per sample.

``checkpoint.h5`` (restart data for the runner)
    ``arrays/<key>``: each array bit-exact (any dtype h5py can store, any shape, 0-length
    included); root attribute ``meta``: JSON text (NaN kept as the JSON extension token ``NaN``).

Errors: a missing file raises FileNotFoundError; a file that is not HDF5, not a tcd file of the
expected kind or of another schema version raises ValueError; a frame index out of range raises
IndexError; an inconsistent frame or series raises ValueError naming the key, before anything
touches the disk. Every message names the path.
"""
from __future__ import annotations

import contextlib
import csv
import datetime
import errno
import json
import math
import os
import pathlib
import re
import shutil
import sys
import tempfile

import h5py
import numpy as np

SCHEMA_VERSION = 1

WALL_PLANE, WALL_CYLINDER = 0, 1
BOND_INTACT, BOND_BROKEN_TENSION, BOND_BROKEN_SHEAR = 0, 1, 2

FILE_STATES, FILE_SERIES, FILE_CHECKPOINT = "states", "series", "checkpoint"

# group -> symbol of its length in the schema table above
GROUP_SIZE_SYMBOL = {"particles": "N", "walls": "W", "contacts": "M", "bonds": "B"}

# key -> (units, dtype (None: any floating dtype), trailing shape)
FRAME_SCHEMA = {
    "particles/x": ("m", None, (3,)),
    "particles/v": ("m/s", None, (3,)),
    "particles/w": ("rad/s", None, (3,)),
    "particles/radius": ("m", None, ()),
    "particles/layer": ("1", np.int32, ()),
    "particles/sample_index": ("1", np.int32, ()),
    "walls/kind": ("1", np.int32, ()),
    "walls/point": ("m", None, (3,)),
    "walls/direction": ("1", None, (3,)),
    "walls/radius": ("m", None, ()),
    "walls/extent": ("m", None, (2,)),
    "walls/force": ("N", None, (3,)),
    "contacts/i": ("1", np.int32, ()),
    "contacts/j": ("1", np.int32, ()),
    "contacts/impulse": ("N s", None, (3,)),
    "contacts/gap": ("m", None, ()),
    "bonds/i": ("1", np.int32, ()),
    "bonds/j": ("1", np.int32, ()),
    "bonds/state": ("1", np.int8, ()),
    "bonds/impulse": ("N s", None, (3,)),
    "bonds/broken_time": ("s", None, ()),
    "bonds/broken_position": ("m", None, (3,)),
}

# units of a simulation state's arrays (Simulation.state_dict: prepared samples, checkpoints),
# written as each dataset's ``units`` attribute; a key not named here gets none
STATE_UNITS = {
    **{key: unit for key, (unit, _, _) in FRAME_SCHEMA.items()},
    "particles/inv_mass": "1/kg", "particles/inv_inertia": "1/(kg m^2)",
    "particles/f_ext": "N", "particles/system": "1",
    "contacts/impulse_old": "N s", "contacts/start": "1",
    "bonds/g0": "m", "bonds/created": "s", "bonds/area": "m^2", "bonds/d_t": "m",
    "bonds/hd_n": "m", "bonds/hk_n": "m", "bonds/hd_t": "m", "bonds/hk_t": "m",
    "bonds/broken_pos": "m", "bonds/impulse_prev": "N s", "bonds/turn": "N s",
}

_FRAME_META_KEYS = ("time", "step", "stage")
_ROOT_ATTRS = ("schema_version", "tcd_file", "tcd_version", "created", "scenario", "meta")
_STORABLE_KINDS = "biufcSV"  # bool, ints, floats, complex, bytes, compound; not object/unicode

_umask = os.umask(0)
os.umask(_umask)


def _current_umask() -> int:
    """The process's umask now (Linux: /proc/self/status, read without changing it), else
    the one it had when this module was imported (setting it to read it would race with
    other threads' file creation)."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return _umask


# --- atomic writes ---------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path, suffix: str = ".tmp"):
    """Yield a temporary path beside `path`; on success fsync it and ``os.replace`` it onto `path`.

    The temporary file exists (empty) when the body starts; the body writes it and closes it. On
    any exception, KeyboardInterrupt included, the temporary file is removed, `path` is untouched
    and the exception propagates. The result gets the mode of the file it replaces (or the default
    mode from the umask). `suffix` ends the temporary's name (a writer that picks its format
    from the extension, such as imageio, needs the target's).
    """
    target = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(target))
    if os.path.isdir(target):               # os.replace would fail only after all the work
        raise IsADirectoryError(errno.EISDIR, "is a directory, not a file", target)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(target)}.", suffix=suffix,
                                   dir=directory)
    except OSError as exc:                  # named by the path asked for, not the temporary
        raise type(exc)(exc.errno, exc.strerror, target) from None
    os.close(fd)
    try:
        yield tmp
        try:
            mode = os.stat(target).st_mode & 0o7777
        except FileNotFoundError:
            mode = 0o666 & ~_current_umask()
        os.chmod(tmp, mode)
        _fsync_file(tmp)
        os.replace(tmp, target)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        if isinstance(exc, OSError) and type(exc).__module__ == "builtins" and \
                exc.errno is not None and exc.filename in (None, tmp):
            # the disk full (or refusing) while the temporary was written: name the target
            raise type(exc)(exc.errno, exc.strerror, target) from None
        raise
    _fsync_dir(directory)


#: HDF5 files up to this size are built in memory by hdf5_writer; larger ones are written by
#: HDF5 on the disk, after a check of the free space (in memory, an append copies the file
#: five times, which costs more than the disk's one copy once the file is large: an append
#: to a states file of 100-250 MB took 0.4-3 s against 0.15-0.4 s on the disk, session 70)
IN_MEMORY_BYTES = 32 * 2**20
#: the memory a file held by hdf5_writer grows by at a time
_CORE_BLOCK = 2**20


@contextlib.contextmanager
def hdf5_writer(tmp, source=None, size: int = 0):
    """Yield a writable h5py.File to go to the file `tmp`: empty, or a copy of the file `source`
    (to append to); `size`: the bytes the file will about hold.

    Up to IN_MEMORY_BYTES the file is held in memory (HDF5's core driver without a backing
    store) and its image goes to `tmp` in one write of Python's own, so HDF5 never writes to
    the disk: a disk that fills up fails in Python with a plain OSError (errno ENOSPC), where
    HDF5's own writes failed in its close, left the library holding the file, printed
    "Exception ignored" tracebacks naming the temporary, and once ended the process in a
    segmentation fault (a run on a full file system, session 70). Larger files are written by
    HDF5 on the disk once the free space has been seen to hold them. Used inside atomic_path,
    which names the target in the error and removes `tmp`."""
    if size > IN_MEMORY_BYTES:
        if source is not None:
            shutil.copyfile(source, tmp)
        grows = size - os.path.getsize(tmp)
        if shutil.disk_usage(os.path.dirname(os.path.abspath(tmp))).free < 1.1 * grows + 2**24:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), tmp)
        with h5py.File(tmp, "a" if source is not None else "w") as f:
            yield f
        return
    if source is None:
        f = h5py.File(tmp, "w", driver="core", block_size=_CORE_BLOCK, backing_store=False)
    else:
        # h5py has no call that opens a file image; HDF5 takes the image only under a name
        # that no file on the disk has
        fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
        fapl.set_fapl_core(block_size=_CORE_BLOCK, backing_store=False)
        with open(source, "rb") as fh:
            fapl.set_file_image(fh.read())
        name = os.fsencode(os.fspath(tmp)) + b".image"
        f = h5py.File(h5py.h5f.open(name, h5py.h5f.ACC_RDWR, fapl=fapl))
    try:
        yield f
        f.flush()
        image = f.id.get_file_image()
    finally:
        f.close()
    with open(tmp, "wb") as fh:
        fh.write(image)


# the name atomic_path gives its temporary: "." + the target's name + "." + mkstemp's eight
# characters + ".tmp"
_TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


def stale_temporaries(directory) -> list[pathlib.Path]:
    """The temporaries of atomic_path in `directory` (read only: a writer may be using one)."""
    return [path for path in sorted(pathlib.Path(directory).glob(".*.tmp"))
            if _TEMPORARY.fullmatch(path.name) and path.is_file()]


def remove_stale_temporaries(directory) -> list[pathlib.Path]:
    """Remove the temporaries that writers killed hard (SIGKILL, a power cut) left in
    `directory` (atomic_path removes its own on any exception, but not when its process is
    killed); return them. Call only while holding the directory's run lock, so that no other
    tcd process is writing there."""
    removed = []
    for path in sorted(pathlib.Path(directory).glob(".*.tmp")):
        if _TEMPORARY.fullmatch(path.name) and path.is_file():
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
                removed.append(path)
    return removed


def _fsync_file(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(directory):
    # Makes the rename durable; not every platform/filesystem allows fsync on a directory.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# --- JSON ------------------------------------------------------------------------------------
def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def _json_finite(obj):
    """Copy of `obj` with NaN and infinities replaced by None (JSON has no such numbers)."""
    if isinstance(obj, dict):
        return {str(k): _json_finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_finite(v) for v in obj]
    if isinstance(obj, (np.ndarray, np.generic)):
        return _json_finite(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(path, obj) -> None:
    """Write `obj` as JSON (indent 2, NaN and infinities as null), atomically."""
    text = json.dumps(_json_finite(obj), indent=2, allow_nan=False, default=_json_default)
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")


def differences(old, new, prefix="", base: int = 0) -> list:
    """Every leaf where two JSON-like values differ, as ``"a.b[2]: old -> new"`` lines (dicts
    key by key, lists of equal length item by item, numbered from `base`: 1 for scenario keys,
    as the scenario's own errors name them); [] when they are equal."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            out += differences(old.get(k), new.get(k), f"{prefix}.{k}" if prefix else str(k),
                               base)
        return out
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        out = []
        for k, (a, b) in enumerate(zip(old, new)):
            out += differences(a, b, f"{prefix}[{k + base}]", base)
        return out
    return [] if old == new else [f"{prefix}: {old!r} -> {new!r}"]


def shown_differences(changed: list, limit: int = 6) -> str:
    """The first `limit` lines of :func:`differences`, joined, and how many more there are."""
    more = len(changed) - limit
    return "; ".join(changed[:limit]) + (f"; and {more} more" if more > 0 else "")


def branch_origin(record: dict, *, step: bool = False) -> str:
    """Where a sample of a `tcd run --from` run went on from, worded once for every place that
    says it (`tcd run --from`'s report, `tcd info`, `tcd compare`): `record` is the last entry of
    its summary's `branched_from` (tcd.branch), the text "from RUN at t = T s[ (step S, stage K,
    phase P)][, the ring at D mm]". A record missing a key raises KeyError, one with a value
    that is not a number TypeError or ValueError."""
    text = f"from {record['run']} at t = {float(record['time']):.4f} s"
    if step:
        phase = record.get("phase")
        text += (f" (step {int(record['step'])}, stage {record['stage']}"
                 f"{', phase ' + str(phase) if phase else ''})")
    if "displacement_mm" in record:
        text += f", the ring at {float(record['displacement_mm']):.4g} mm"
    return text


# --- shared checks ---------------------------------------------------------------------------
def created_time() -> str:
    """The files' `created` time (UTC): now, or SOURCE_DATE_EPOCH (seconds since 1970, the
    reproducible-builds convention) when it is set, so that the same run writes the same bytes
    (a check by checksum, `h5diff` of the attributes, a build cache). A value that is not a
    whole number of seconds is refused, naming it."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if epoch:
        try:
            stamp = datetime.datetime.fromtimestamp(int(epoch), datetime.timezone.utc)
        except (ValueError, OverflowError, OSError):
            raise ValueError(f"SOURCE_DATE_EPOCH={epoch!r}: expected whole seconds since "
                             "1970-01-01 UTC") from None
        return stamp.isoformat(timespec="seconds")
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _default_version(tcd_version: str) -> str:
    # Use the package's version when it is already loaded; never import it (it imports Taichi).
    if tcd_version:
        return str(tcd_version)
    return str(getattr(sys.modules.get("tcd"), "__version__", ""))


def _write_header(f: h5py.File, kind: str, tcd_version: str = "") -> None:
    """The attributes every tcd file starts with: schema, kind, writer version, creation time."""
    f.attrs["schema_version"] = SCHEMA_VERSION
    f.attrs["tcd_file"] = kind
    f.attrs["tcd_version"] = _default_version(tcd_version)
    f.attrs["created"] = created_time()


def _check_dataset_key(key, where: str, *, need_group: bool) -> str:
    if not isinstance(key, str):
        raise ValueError(f"{where}: key {key!r} is not a string")
    parts = key.split("/")
    if key.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"{where}: key {key!r} is not a valid dataset path")
    if need_group and len(parts) < 2:
        raise ValueError(f"{where}: key {key!r} must name a group, e.g. 'particles/{key}'")
    return key


def _dataset(group, key: str, arr: np.ndarray):
    """Create dataset `key`; numeric arrays get a Fletcher-32 checksum (HDF5's own filter, on
    chunked storage): a byte damaged on disk is then a read error, not silently wrong
    numbers. Every HDF5 reader checks it; files written without it read as before."""
    if arr.ndim >= 1 and arr.size > 0 and arr.dtype.kind in "biuf":
        return group.create_dataset(key, data=arr, chunks=True, fletcher32=True)
    return group.create_dataset(key, data=arr)


def _as_storable(key: str, value, where: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in _STORABLE_KINDS:
        raise ValueError(f"{where}: key {key!r} has dtype {arr.dtype}, which HDF5 cannot store "
                         f"(use numbers or bytes)")
    return arr


def _open_tcd(path, kind: str) -> h5py.File:
    """Open `path` read-only after checking it is a tcd file of `kind` and schema version 1."""
    path = os.fspath(path)
    if not os.path.exists(path):
        what = f"tcd {kind} file" if kind else "tcd file"
        raise FileNotFoundError(errno.ENOENT, f"no such {what}", path)
    if os.path.isdir(path) or not h5py.is_hdf5(path):
        raise ValueError(f"{path}: not an HDF5 file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ValueError(f"{path}: HDF5 file cannot be opened (truncated or corrupt?): {exc}") \
            from exc
    try:
        _check_schema(f, path, kind)
    except BaseException:
        f.close()
        raise
    return f


def _check_schema(f: h5py.File, path: str, kind: str | None) -> str:
    version = f.attrs.get("schema_version")
    if version is None:
        raise ValueError(f"{path}: missing schema_version attribute (not a tcd file)")
    try:
        known = np.ndim(version) == 0 and int(version) == SCHEMA_VERSION
    except (TypeError, ValueError):
        known = False
    if not known:
        shown = version.tolist() if isinstance(version, np.ndarray | np.generic) else version
        raise ValueError(f"{path}: unknown schema_version {shown!r} "
                         f"(this tcd reads version {SCHEMA_VERSION})")
    found = _file_kind(f)
    if found is None:
        raise ValueError(f"{path}: schema_version {SCHEMA_VERSION} but no tcd_file attribute")
    if kind is not None and found != kind:
        raise ValueError(f"{path}: is a tcd {found} file, expected a {kind} file")
    return found


def _file_kind(f: h5py.File) -> str | None:
    kind = f.attrs.get("tcd_file")
    if kind is not None:
        return kind.decode() if isinstance(kind, bytes) else str(kind)
    if "frames" in f:  # written by hand without the tcd_file attribute
        return FILE_STATES
    return None


def _read(ds: h5py.Dataset) -> np.ndarray:
    """The whole dataset; a failed checksum (h5py: "filter returned failure during read") is
    an OSError that says the file is damaged and names the file and dataset."""
    try:
        return np.asarray(ds[()])
    except OSError as exc:
        if ds.fletcher32 and "filter returned failure" in str(exc):
            raise OSError(f"{ds.file.filename}: dataset {ds.name}: checksum mismatch, the file "
                          "is damaged") from None
        raise


def _datasets(group: h5py.Group) -> dict:
    """All datasets under `group`, keyed by their path relative to it, read as NumPy arrays."""
    out = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            out[name] = _read(obj)

    group.visititems(visit)
    return out


def check_readable(path) -> None:
    """Read the tcd file `path` whole (every attribute, every dataset, checksums checked) and
    raise ValueError naming it when a part cannot be read: a file damaged on disk or by a
    program other than tcd (tcd's own writes are atomic). h5py reports such damage as
    OSError, RuntimeError ("Object visitation failed") or KeyError, depending on the byte hit;
    a resumed run checks the files it goes on from with it before it writes anything."""
    path = os.fspath(path)

    def visit(name, obj):
        dict(obj.attrs)
        if isinstance(obj, h5py.Dataset):
            _read(obj)

    try:
        with _open_tcd(path, None) as f:
            dict(f.attrs)
            f.visititems(visit)
    except (OSError, RuntimeError, KeyError) as exc:
        if isinstance(exc, FileNotFoundError):
            raise
        text = str(exc)
        raise ValueError(text if text.startswith(path) else
                         f"{path}: cannot read ({type(exc).__name__}: {text}); the file is "
                         "damaged") from None


def _units_attr(obj) -> str:
    u = obj.attrs.get("units", "")
    return u.decode() if isinstance(u, bytes) else str(u)


# --- states ----------------------------------------------------------------------------------
def _check_frame(frame: dict, units: dict | None, *, time, step, stage, where: str) -> list:
    """Validate a frame; return [(key, array, units)] ready to store. Raises ValueError."""
    if not isinstance(frame, dict):
        raise ValueError(f"{where}: expected a dict of arrays, got {type(frame).__name__}")
    units = dict(units or {})
    for key, unit in units.items():
        if key in FRAME_SCHEMA and unit != FRAME_SCHEMA[key][0]:
            raise ValueError(f"{where}: units {unit!r} for {key!r} contradict the schema "
                             f"({FRAME_SCHEMA[key][0]!r})")
    if "particles/x" not in frame:
        raise ValueError(f"{where}: key 'particles/x' is required")
    try:
        float(time)
        if int(step) != step:
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(f"{where}: time must be a number and step an integer, "
                         f"got time={time!r}, step={step!r}") from None
    if not isinstance(stage, str):
        raise ValueError(f"{where}: stage must be a string, got {stage!r}")
    return _check_arrays(frame, units, where)


def check_state(arrays: dict, where: str, *, wall_slots: int | None = None,
                finite_positions: bool = True) -> None:
    """Check the state arrays read from a file (a states file's frame, a checkpoint's or a
    prepared sample's arrays) against the schema before anything indexes with them: shapes,
    dtypes, lengths that must agree, and particle and wall indices in range. `wall_slots`: the
    wall indices contacts may use (default: the frame's walls; a checkpoint keeps its walls
    in its meta). `finite_positions=False` lets non-finite positions pass (a frame of a run
    that diverged, to be looked at). Keys outside FRAME_SCHEMA are not checked. Raises
    ValueError naming `where`."""
    _check_arrays({k: v for k, v in arrays.items() if k in FRAME_SCHEMA}, {}, where,
                  wall_slots=wall_slots)
    if "particles/radius" not in arrays:
        raise ValueError(f"{where}: key 'particles/radius' is required")
    r, x = np.asarray(arrays["particles/radius"]), np.asarray(arrays["particles/x"])
    if not np.all(np.isfinite(r) & (r > 0)):
        bad = int(np.count_nonzero(~(np.isfinite(r) & (r > 0))))
        raise ValueError(f"{where}: key 'particles/radius' holds {bad} radii that are not "
                         "positive and finite")
    if finite_positions and not np.all(np.isfinite(x)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(x), axis=1)))
        raise ValueError(f"{where}: key 'particles/x' holds {bad} positions that are not finite "
                         "(a state of a run that diverged?)")


def meta_wall_slots(arrays, meta) -> int | None:
    """The wall indices a checkpoint's contacts may use, for `check_state`: None (the walls its
    arrays hold) when it has `walls/` arrays, else the count of the walls of its meta."""
    walls = meta.get("walls") if isinstance(meta, dict) else None
    if isinstance(walls, list) and not any(k.startswith("walls/") for k in arrays):
        return len(walls)
    return None


def _check_arrays(frame: dict, units: dict, where: str, *, wall_slots: int | None = None) -> list:
    if "particles/x" not in frame:
        raise ValueError(f"{where}: key 'particles/x' is required")
    sizes: dict[str, tuple[int, str]] = {}  # group -> (length, key that fixed it)
    prepared = []
    for key, value in frame.items():
        _check_dataset_key(key, where, need_group=True)
        arr = _as_storable(key, value, where)
        group = key.split("/", 1)[0]
        if key in FRAME_SCHEMA:
            unit, dtype, trailing = FRAME_SCHEMA[key]
            expected = f"({GROUP_SIZE_SYMBOL[group]}{''.join(f',{t}' for t in trailing)})"
            if arr.ndim != 1 + len(trailing) or arr.shape[1:] != trailing:
                raise ValueError(f"{where}: key {key!r} has shape {arr.shape}, expected {expected}")
            if dtype is None:
                if arr.dtype.kind != "f":
                    raise ValueError(f"{where}: key {key!r} has dtype {arr.dtype}, "
                                     f"expected float32 or float64")
            else:
                arr = _to_int(key, arr, dtype, where)
        else:
            unit = str(units.get(key, "1"))
        if group in GROUP_SIZE_SYMBOL and arr.ndim >= 1:
            length, first = sizes.setdefault(group, (arr.shape[0], key))
            if arr.shape[0] != length:
                raise ValueError(f"{where}: key {key!r} has length {arr.shape[0]} but {first!r} "
                                 f"has {length} ({GROUP_SIZE_SYMBOL[group]} must agree)")
        prepared.append((key, arr, unit))

    n = sizes["particles"][0]
    n_walls = sizes.get("walls", (0, ""))[0] if wall_slots is None else int(wall_slots)
    arrays = {key: arr for key, arr, _ in prepared}
    for key, upper in (("contacts/i", n), ("contacts/j", n + n_walls),
                       ("bonds/i", n), ("bonds/j", n)):
        idx = arrays.get(key)
        if idx is not None and idx.size and (idx.min() < 0 or idx.max() >= upper):
            raise ValueError(f"{where}: key {key!r} has indices in [{idx.min()}, {idx.max()}], "
                             f"expected [0, {upper}) with N={n}, W={n_walls}")
    state = arrays.get("bonds/state")
    if state is not None and state.size and not np.isin(
            state, (BOND_INTACT, BOND_BROKEN_TENSION, BOND_BROKEN_SHEAR)).all():
        raise ValueError(f"{where}: key 'bonds/state' has values outside {{0, 1, 2}}")
    kind = arrays.get("walls/kind")
    if kind is not None and kind.size:
        from .walls import KINDS
        if not np.isin(kind, sorted(KINDS.values())).all():
            known = ", ".join(f"{v} {k}" for k, v in sorted(KINDS.items(), key=lambda kv: kv[1]))
            raise ValueError(f"{where}: key 'walls/kind' has values outside {{{known}}}: "
                             f"{sorted(set(kind.tolist()) - set(KINDS.values()))[:5]}")
    return prepared


def _to_int(key: str, arr: np.ndarray, dtype, where: str) -> np.ndarray:
    if arr.dtype == dtype:
        return arr
    if arr.dtype.kind not in "iu":
        raise ValueError(f"{where}: key {key!r} has dtype {arr.dtype}, expected {np.dtype(dtype)}")
    info_ = np.iinfo(dtype)
    if arr.size and (arr.min() < info_.min or arr.max() > info_.max):
        raise ValueError(f"{where}: key {key!r} has values outside the {np.dtype(dtype)} range")
    return arr.astype(dtype)


def _frame_names(f: h5py.File, path: str) -> list[str]:
    frames = f.get("frames")
    if not isinstance(frames, h5py.Group):
        raise ValueError(f"{path}: states file without a 'frames' group")
    names = list(frames.keys())
    if not all(name.isdigit() for name in names):
        raise ValueError(f"{path}: unexpected group names under 'frames': {names[:5]}")
    return sorted(names, key=int)


def append_frame(path, frame: dict, *, time, step, stage, scenario_text: str = "",
                 tcd_version: str = "", units: dict | None = None) -> int:
    """Append one snapshot to the states file `path` (created if absent); return its index.

    `frame` maps dataset paths ("particles/x", ...) to arrays (see the module docstring).
    `scenario_text` and `tcd_version` are stored when the file is created and ignored after.
    `units` gives units of extra keys; entries for keys not in `frame` are ignored.
    """
    path = os.fspath(path)
    prepared = _check_frame(frame, units, time=time, step=step, stage=stage,
                            where=f"{path}: frame")
    if os.path.exists(path):
        with _open_tcd(path, FILE_STATES) as f:
            index = len(_frame_names(f, path))
        with atomic_path(path) as tmp:
            size = os.path.getsize(path) + sum(arr.nbytes for _, arr, _ in prepared)
            with hdf5_writer(tmp, source=path, size=size) as f:
                _write_frame(f, index, prepared, time, step, stage)
    else:
        index = 0
        with atomic_path(path) as tmp:
            with hdf5_writer(tmp, size=sum(arr.nbytes for _, arr, _ in prepared)) as f:
                _write_header(f, FILE_STATES, tcd_version)
                f.attrs["scenario"] = str(scenario_text)
                f.create_group("frames")
                _write_frame(f, index, prepared, time, step, stage)
    return index


def _write_frame(f: h5py.File, index: int, prepared: list, time, step, stage) -> None:
    group = f["frames"].create_group(f"{index:06d}")
    group.attrs["time"] = float(time)
    group.attrs["time_units"] = "s"
    group.attrs["step"] = int(step)
    group.attrs["stage"] = stage
    for key, arr, unit in prepared:
        ds = _dataset(group, key, arr)
        ds.attrs["units"] = unit


def frame_count(path) -> int:
    """Number of frames in the states file `path`."""
    with _open_tcd(path, FILE_STATES) as f:
        return len(_frame_names(f, os.fspath(path)))


def last_frame_clock(path) -> tuple[float, int, str] | None:
    """(time, step, stage) of the last frame of the states file `path` (None: no file, or
    no frame), read from its attributes only."""
    path = os.fspath(path)
    if not os.path.exists(path):
        return None
    with _open_tcd(path, FILE_STATES) as f:
        names = _frame_names(f, path)
        if not names:
            return None
        attrs = f["frames"][names[-1]].attrs
        return float(attrs["time"]), int(attrs["step"]), str(attrs["stage"])


def keep_frames(path, count: int) -> int:
    """Cut the states file `path` back to its first `count` frames (atomically: the file is
    either as it was or cut); returns how many frames were dropped. A resumed run calls it
    with the number of frames its checkpoint was written after, so that frames written
    between that checkpoint and a hard kill are not written twice."""
    path = os.fspath(path)
    with _open_tcd(path, FILE_STATES) as f:
        names = _frame_names(f, path)
    if count < 0 or count > len(names):
        raise ValueError(f"{path}: cannot keep {count} frames of {len(names)}")
    if count == len(names):
        return 0
    with atomic_path(path) as tmp:
        with h5py.File(path, "r") as src, hdf5_writer(tmp, size=os.path.getsize(path)) as dst:
            for key, value in src.attrs.items():
                dst.attrs[key] = value
            for key in src:
                if key != "frames":
                    src.copy(src[key], dst, key)
            frames = dst.create_group("frames")
            for key, value in src["frames"].attrs.items():
                frames.attrs[key] = value
            for name in names[:count]:
                src.copy(src["frames"][name], frames, name)
    return len(names) - count


def read_frame(path, index: int = -1) -> dict:
    """Frame `index` (negative counts from the end) as the flat dict it was written from.

    Arrays come back with the dtype and bytes they were stored with; the keys "time" (float),
    "step" (int) and "stage" (str) are added.
    """
    path = os.fspath(path)
    with _open_tcd(path, FILE_STATES) as f:
        names = _frame_names(f, path)
        count = len(names)
        k = int(index) + count if int(index) < 0 else int(index)
        if not 0 <= k < count:
            raise IndexError(f"{path}: frame index {index} out of range ({count} frames)")
        group = f["frames"][names[k]]
        out = _datasets(group)
        out["time"] = float(group.attrs["time"])
        out["step"] = int(group.attrs["step"])
        out["stage"] = str(group.attrs["stage"])
    return out


# --- time series -----------------------------------------------------------------------------
def write_series(path_h5, series: dict, *, units: dict | None = None, attrs: dict | None = None,
                 csv_path=None, csv_keys=None) -> None:
    """Write time series (one dataset per key, same first-axis length) atomically.

    `units` maps keys to unit strings ("1" by default; entries for absent keys are ignored).
    `attrs` become root attributes. With `csv_path`, a CSV twin holds the 1-D columns `csv_keys`
    (all 1-D keys by default) under a header "key [units]".
    """
    path_h5 = os.fspath(path_h5)
    where = f"{path_h5}: series"
    units = dict(units or {})
    arrays = {}
    length, first = None, None
    for key, value in series.items():
        _check_dataset_key(key, where, need_group=False)
        arr = _as_storable(key, value, where)
        if arr.ndim < 1:
            raise ValueError(f"{where}: key {key!r} is a scalar, expected an array over samples")
        if length is None:
            length, first = arr.shape[0], key
        elif arr.shape[0] != length:
            raise ValueError(f"{where}: key {key!r} has length {arr.shape[0]} but {first!r} "
                             f"has {length}")
        arrays[key] = arr
    root_attrs = {}
    for name, value in (attrs or {}).items():
        if name in _ROOT_ATTRS:
            raise ValueError(f"{where}: attribute {name!r} is reserved")
        root_attrs[str(name)] = _attr_value(value)
    if csv_keys is not None and csv_path is None:
        raise ValueError(f"{where}: csv_keys given without csv_path")
    if csv_path is not None:
        if csv_keys is None:
            csv_keys = [k for k, a in arrays.items() if a.ndim == 1]
        for key in csv_keys:
            if key not in arrays:
                raise ValueError(f"{where}: csv key {key!r} is not a series key")
            if arrays[key].ndim != 1:
                raise ValueError(f"{where}: csv key {key!r} has shape {arrays[key].shape}, "
                                 f"only 1-D series fit a CSV column")

    # the CSV twin is written first and both files replace the old ones only once both are
    # whole: a disk that filled at the CSV left a new .h5 beside a missing or stale .csv
    # (session 72's review)
    with contextlib.ExitStack() as stack:
        if csv_path is not None:
            tmp_csv = stack.enter_context(atomic_path(csv_path))
            with open(tmp_csv, "w", newline="", encoding="utf-8") as fh:
                writer = csv.writer(fh)
                writer.writerow([f"{k} [{units.get(k, '1')}]" for k in csv_keys])
                columns = [arrays[k] for k in csv_keys]
                for row in zip(*columns):
                    writer.writerow([_csv_cell(v) for v in row])
        with atomic_path(path_h5) as tmp:
            with hdf5_writer(tmp, size=sum(arr.nbytes for arr in arrays.values())) as f:
                _write_header(f, FILE_SERIES)
                for name, value in root_attrs.items():
                    f.attrs[name] = value
                for key, arr in arrays.items():
                    ds = _dataset(f, key, arr)
                    ds.attrs["units"] = str(units.get(key, "1"))


def _attr_value(value):
    if isinstance(value, (str, bytes, bool, int, float, np.generic)):
        return value
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
        return value
    return json.dumps(value, default=_json_default)


def _csv_cell(value) -> str:
    # str() of a NumPy scalar is the shortest text that reads back to the same value.
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.bool_):
        return str(int(value))
    return str(value)


def read_series(path) -> dict:
    """All series of `path` as {key: array} (as written)."""
    with _open_tcd(path, FILE_SERIES) as f:
        return _datasets(f)


# --- checkpoints -----------------------------------------------------------------------------
def save_checkpoint(path, arrays: dict, meta: dict) -> None:
    """Store `arrays` bit-exact and `meta` as JSON text in one HDF5 file, atomically."""
    where = f"{os.fspath(path)}: checkpoint"
    prepared = {}
    for key, value in arrays.items():
        _check_dataset_key(key, where, need_group=False)
        prepared[key] = _as_storable(key, value, where)
    try:
        meta_text = json.dumps(meta, default=_json_default)
    except TypeError as exc:
        raise ValueError(f"{where}: meta is not JSON serialisable: {exc}") from exc
    with atomic_path(path) as tmp:
        with hdf5_writer(tmp, size=sum(arr.nbytes for arr in prepared.values())) as f:
            _write_header(f, FILE_CHECKPOINT)
            f.attrs["meta"] = meta_text
            group = f.create_group("arrays")
            for key, arr in prepared.items():
                ds = _dataset(group, key, arr)
                if key in STATE_UNITS:
                    ds.attrs["units"] = STATE_UNITS[key]


def load_checkpoint(path) -> tuple[dict, dict]:
    """(arrays, meta) as given to :func:`save_checkpoint`."""
    path = os.fspath(path)
    with _open_tcd(path, FILE_CHECKPOINT) as f:
        if "arrays" not in f or "meta" not in f.attrs:
            raise ValueError(f"{path}: checkpoint without 'arrays' group or 'meta' attribute")
        try:
            arrays = _datasets(f["arrays"])
        except (RuntimeError, KeyError) as exc:     # h5py's word for a damaged structure
            raise ValueError(f"{path}: cannot read ({type(exc).__name__}: {exc}); the file "
                             "is damaged") from None
        meta = _meta_of(f, path)
    return arrays, meta


def _meta_of(f: h5py.File, path: str):
    """A checkpoint's `meta` attribute, parsed (ValueError naming `path` if it is not JSON)."""
    try:
        return json.loads(f.attrs["meta"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: its 'meta' attribute is not valid JSON ({exc})") from None


def save_figure(fig, path, fmt: str, **kwargs) -> None:
    """Write the matplotlib figure `fig` to `path` (a temporary of atomic_path) as `fmt`:
    drawn in memory first, then written in one write of Python's own, so that a full disk is
    a plain OSError naming `path`. (Matplotlib's PDF writer, failing half way on a full disk,
    raised AttributeError in its clean-up, which hid the OSError: `tcd figures` and `tcd
    compare` ended in a traceback, session 72's review.) Date-free metadata as
    figure_metadata."""
    import io as _bytes_io
    buf = _bytes_io.BytesIO()
    fig.savefig(buf, format=fmt, metadata=figure_metadata(fmt), **kwargs)
    with open(path, "wb") as fh:
        fh.write(buf.getbuffer())


def figure_metadata(fmt: str) -> dict | None:
    """Matplotlib `savefig` metadata that leaves out the date it would write into a PDF, PS
    or SVG, so that the same figure is the same bytes (`tcd figures` twice; PNG has none)."""
    fmt = fmt.lower()
    if fmt in ("pdf", "ps", "eps"):
        return {"CreationDate": None}
    if fmt == "svg":
        return {"Date": None}
    return None


def checkpoint_meta(path) -> tuple[dict, str]:
    """(meta, created) of the checkpoint at `path`, without reading its arrays."""
    path = os.fspath(path)
    with _open_tcd(path, FILE_CHECKPOINT) as f:
        if "meta" not in f.attrs:
            raise ValueError(f"{path}: checkpoint without 'meta' attribute")
        meta = _meta_of(f, path)
        if not isinstance(meta, dict):
            raise ValueError(f"{path}: its 'meta' attribute is not a JSON object")
        return meta, _attr_text(f, "created")


def checkpoint_arrays(path, keys) -> dict:
    """Those of the arrays `keys` that the checkpoint at `path` holds, without reading the
    others (a run's series, `series/<column>`, from a checkpoint of several MB)."""
    path = os.fspath(path)
    with _open_tcd(path, FILE_CHECKPOINT) as f:
        group = f.get("arrays")
        if not isinstance(group, h5py.Group):
            return {}
        return {k: _read(group[k]) for k in keys
                if k in group and isinstance(group[k], h5py.Dataset)}


def checkpoint_shear_series(path, seed=None) -> tuple[dict, object, dict]:
    """(series, smoothing_window_mm, meta) of the shear a checkpoint stopped in: its series so
    far (column -> array, as the series file would hold them) and its shear stage's
    `smoothing_window_mm` as the scenario it ran wrote it (the scenario default where it gave
    none). `seed`: that sample's series in a batch's checkpoint
    (batch_checkpoint.h5, `series/<seed>/`); None for one sample's checkpoint.h5.

    Raises OSError when the file cannot be read, ValueError when it was written outside a
    shear stage, does not hold that sample, or its stage cannot be told (tcd info's peak so far
    of a stopped shear, tcd compare's curve of one)."""
    import tomllib
    meta, _ = checkpoint_meta(path)
    batched = "seeds" in meta
    try:
        stages = [st for st in tomllib.loads(meta["scenario_text"]).get("stage", [])
                  if isinstance(st, dict)]
        if batched:     # a batch runs a scenario whose only stage is a shear
            if seed is None or int(seed) not in meta["seeds"]:
                raise ValueError(f"no sample {seed} in the batch of seeds {meta['seeds']}")
            k, prefix = 0, f"series/{int(seed)}/"
            keys = (meta.get("series_keys") or {}).get(str(int(seed)))
        else:
            k, keys, prefix = meta["stage"], meta.get("series_keys"), "series/"
        if not isinstance(k, int) or isinstance(k, bool) or k < 0:
            raise TypeError(f"stage {k!r}")
        stage = stages[k]
    except (KeyError, IndexError, TypeError, AttributeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{os.fspath(path)}: its stage cannot be read ({exc!r})") from None
    if stage.get("kind") != "shear":
        raise ValueError(f"{os.fspath(path)}: written in a {stage.get('kind')!r} stage, "
                         "not a shear")
    if not isinstance(keys, list) or not all(isinstance(key, str) for key in keys):
        keys = ["time", "displacement", "shear_stress"]
    series = checkpoint_arrays(path, [prefix + key for key in keys])
    from .config import ShearStage
    window = stage.get("smoothing_window_mm", ShearStage.model_fields["smoothing_window_mm"].default)
    return {key[len(prefix):]: v for key, v in series.items()}, window, meta


# --- summary ---------------------------------------------------------------------------------
def info(path) -> str:
    """A readable multi-line summary of a tcd states, series or checkpoint file."""
    path = os.fspath(path)
    with _open_tcd(path, None) as f:
        kind = _file_kind(f)
        head = (f"{path}: tcd {kind} file, schema_version {int(f.attrs['schema_version'])}, "
                f"tcd_version {_attr_text(f, 'tcd_version') or '?'}, "
                f"created {_attr_text(f, 'created') or '?'}")
        if kind == FILE_STATES:
            body = _info_states(f, path)
        elif kind == FILE_SERIES:
            body = _info_series(f)
        else:
            body = _info_checkpoint(f)
    return "\n".join([head] + body)


def _attr_text(obj, name: str) -> str:
    value = obj.attrs.get(name, "")
    return value.decode() if isinstance(value, bytes) else str(value)


def _info_states(f: h5py.File, path: str) -> list[str]:
    names = _frame_names(f, path)
    scenario = _attr_text(f, "scenario")
    lines = [f"scenario: {len(scenario.splitlines())} lines of TOML" if scenario
             else "scenario: (none)"]
    if not names:
        return lines + ["frames: 0"]
    groups = [f["frames"][n] for n in names]
    times = [float(g.attrs["time"]) for g in groups]
    steps = [int(g.attrs["step"]) for g in groups]
    stages = list(dict.fromkeys(str(g.attrs["stage"]) for g in groups))
    lines.append(f"frames: {len(names)}, time {min(times):.6g} .. {max(times):.6g} s, "
                 f"step {min(steps)} .. {max(steps)}")
    lines.append(f"stages: {', '.join(stages)}")
    last = groups[-1]
    diverged = []
    for k, group in enumerate(groups):      # every frame's arrays, as export and render read them
        frame = _datasets(group)
        check_state(frame, f"{path}: frame {k}", finite_positions=False)
        if not np.all(np.isfinite(frame["particles/x"])):
            diverged.append(k)

    def length(key):
        return last[key].shape[0] if key in last else 0

    lines.append(f"last frame {names[-1]} (t = {times[-1]:.6g} s, stage {last.attrs['stage']}): "
                 f"{length('particles/x')} particles, {length('walls/kind')} walls, "
                 f"{length('contacts/i')} contacts")
    if "bonds/state" in last:
        state = _read(last["bonds/state"])
        lines.append(f"bonds: {state.size} (intact {int(np.sum(state == BOND_INTACT))}, "
                     f"broken in tension {int(np.sum(state == BOND_BROKEN_TENSION))}, "
                     f"broken in shear {int(np.sum(state == BOND_BROKEN_SHEAR))})")
    else:
        lines.append("bonds: none")
    if diverged:
        shown = ", ".join(map(str, diverged[:5])) + (" ..." if len(diverged) > 5 else "")
        lines.append(f"warning: {len(diverged)} frame(s) hold positions that are not finite (a "
                     f"run that diverged?): {shown}")
    return lines


def _info_series(f: h5py.File) -> list[str]:
    entries = []
    f.visititems(lambda name, obj: entries.append((name, obj))
                 if isinstance(obj, h5py.Dataset) else None)
    lines = [f"series: {len(entries)} keys"]
    for name, value in f.attrs.items():
        if name not in _ROOT_ATTRS:
            lines.append(f"attr {name} = {value!r}"[:200])
    for name, ds in entries:
        data = _read(ds)
        text = f"  {name} [{_units_attr(ds)}]: length {ds.shape[0]}"
        if data.dtype.kind in "biuf" and data.size:
            values = data.astype(float)
            finite = values[np.isfinite(values)]
            if finite.size:
                text += f", min {finite.min():.6g}, max {finite.max():.6g}"
            if data.ndim == 1:
                text += f", last {values[-1]:.6g}"
        lines.append(text)
    return lines


def _info_checkpoint(f: h5py.File) -> list[str]:
    entries = []
    if "arrays" in f:
        f["arrays"].visititems(lambda name, obj: entries.append((name, obj))
                               if isinstance(obj, h5py.Dataset) else None)
    try:
        meta = json.loads(f.attrs.get("meta", "{}"))
    except (TypeError, ValueError):         # not JSON, or not text (a number)
        meta = None
    keys = ", ".join(map(str, meta)) if isinstance(meta, dict) else "(unreadable)"
    lines = [f"meta keys: {keys}", f"arrays: {len(entries)}"]
    lines += [f"  {name}: {ds.dtype} {ds.shape}" for name, ds in entries]
    datasets = {name: ds for name, ds in entries}
    try:
        check_state({k: _read(ds) for k, ds in datasets.items() if k in FRAME_SCHEMA},
                    "arrays", wall_slots=meta_wall_slots(datasets, meta))
    except (ValueError, OSError) as exc:
        return lines + [f"sample: not read ({exc})"]
    return lines + _info_sample(datasets)


_SAMPLE_KEYS = ("particles/x", "particles/radius", "particles/layer", "walls/kind", "walls/point",
                "walls/direction", "walls/radius", "walls/force")


def _info_sample(ds: dict) -> list[str]:
    """The sample a checkpoint holds, when it is grains in a mould (a cylinder between a bottom
    and a top plate, as `prepared.h5` files are): its size, packing, courses and overlaps, read
    from the arrays alone (no scenario needed). Nothing for other checkpoints."""
    if not all(k in ds for k in _SAMPLE_KEYS):
        return []
    from . import observables as obs
    from .walls import CYLINDER, PLANE
    x, r, layer = (_read(ds[k]) for k in _SAMPLE_KEYS[:3])
    kind, point, direction, radius, force = (_read(ds[k]) for k in _SAMPLE_KEYS[3:])
    cyl = np.flatnonzero(kind == CYLINDER)
    top = np.flatnonzero((kind == PLANE) & (direction[:, 2] < -0.5))
    bottom = np.flatnonzero((kind == PLANE) & (direction[:, 2] > 0.5))
    if len(x) == 0 or len(cyl) != 1 or len(top) != 1 or len(bottom) != 1:
        return []                       # not one mould (a sheared sample has two rings)
    R = float(radius[cyl[0]])
    z0, H = float(point[bottom[0], 2]), float(point[top[0], 2])
    if not (H > z0 and R > 0):          # no room between the plates or inside the mould
        return []
    ids = sorted(set(layer.tolist()))
    counts = [int(np.count_nonzero(layer == L)) for L in ids]
    peaks = [z0] + obs.layer_highest(x, r, layer)
    highest = max(peaks[1:])
    p99 = [z0] + obs.layer_tops(x, r, layer)
    mm = lambda v: " / ".join(f"{1e3 * u:.1f}" for u in v)
    plate_gap = (f"{1e3 * (H - highest):.1f} mm below the top plate" if H - highest >= 5e-5
                 else "at the top plate")
    # through the mould (about its own axis) or a plate by more than 1 % of d_min
    outside = obs.outside(x, r, R, z0, H, axis=point[cyl[0], :2])
    lines = ["sample (grains in a mould, read from the arrays):",
             f"  {len(x)} particles ({' + '.join(map(str, counts))} in courses {ids}), diameters "
             f"{2e3 * r.min():.3g} to {2e3 * r.max():.3g} mm",
             f"  mould: diameter {2e3 * R:.1f} mm, plates at {1e3 * z0:.1f} and {1e3 * H:.1f} mm "
             f"(force of the grains on the top plate {force[top[0], 2]:.3g} N)",
             f"  packing between the plates {obs.packing_fraction(x, r, R, z0, H):.3f}; highest grain "
             f"top {1e3 * highest:.1f} mm ({plate_gap}), "
             f"packing below it {obs.packing_fraction(x, r, R, z0, min(highest, H)):.3f}",
             f"  courses by their highest grain {mm(np.diff(peaks))} mm; by their 99th-percentile "
             f"tops {mm(np.diff(p99))} mm",
             f"  outside the mould: {outside} (by more than 1 % of the smallest diameter)"]
    if "contacts/gap" in ds and "contacts/j" in ds:
        gap, j = _read(ds["contacts/gap"]), _read(ds["contacts/j"])
        loaded = ""
        if "contacts/i" in ds and "contacts/impulse" in ds:
            z = obs.coordination_number(None, j, len(x), obs.carries_force(
                _read(ds["contacts/i"]), j, _read(ds["contacts/impulse"]), x))
            loaded = f" ({z:.2f} carrying a force)"
        lines.append(f"  contacts: {len(gap)}, coordination {obs.coordination_number(None, j, len(x)):.2f}"
                     f"{loaded}, largest overlap {100 * obs.max_overlap(gap) / (2 * r.min()):.2f} % "
                     f"of the smallest diameter")
    return lines


def file_record(path) -> dict:
    """Where an input file was read from and what it held: its absolute path, size and
    SHA-256 (a run's record of the prepared sample it sheared, so that a later reader can tell
    whether the file there is still that one)."""
    import hashlib
    path = pathlib.Path(path).resolve()
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return {"path": str(path), "bytes": path.stat().st_size, "sha256": digest.hexdigest()}
