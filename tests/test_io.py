"""tcd.io: schema, bit-exact round trips, crash safety (exceptions, SIGKILL), errors, summaries."""
import csv
import json
import os
import pathlib
import random
import re
import signal
import stat
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from tcd import io

# The SIGKILL child loads io.py by path: it needs neither Taichi nor an installed tcd.
IO_SOURCE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tcd",
                         "io.py")


def nan_with_payload(dtype):
    """A quiet NaN with a non-default payload: survives only a bit-exact copy."""
    base = np.array([np.nan], dtype=dtype)
    bits = base.view(np.uint64 if base.itemsize == 8 else np.uint32)
    bits |= 0x5
    return base[0]


def make_frame(n=7, n_walls=3, n_contacts=9, n_bonds=5, seed=0):
    rng = np.random.default_rng(seed)
    broken_time = np.full(n_bonds, np.nan)
    broken_time[1] = 0.125
    broken_time[3] = nan_with_payload(np.float64)
    broken_position = rng.normal(size=(n_bonds, 3))
    broken_position[0] = np.nan
    return {
        "particles/x": rng.normal(size=(n, 3)),
        "particles/v": rng.normal(size=(n, 3)),
        "particles/w": rng.normal(size=(n, 3)).astype(np.float32),
        "particles/radius": rng.uniform(1e-3, 8e-3, n),
        "particles/layer": np.arange(n, dtype=np.int32) % 2,
        "walls/kind": np.array([0, 0, 1][:n_walls], dtype=np.int32),
        "walls/point": rng.normal(size=(n_walls, 3)),
        "walls/direction": rng.normal(size=(n_walls, 3)),
        "walls/radius": rng.uniform(size=n_walls),
        "walls/extent": rng.uniform(size=(n_walls, 2)),
        "walls/force": rng.normal(size=(n_walls, 3)),
        "contacts/i": rng.integers(0, n, n_contacts).astype(np.int32),
        "contacts/j": rng.integers(0, n + n_walls, n_contacts).astype(np.int32),
        "contacts/impulse": rng.normal(size=(n_contacts, 3)).astype(np.float32),
        "contacts/gap": rng.normal(size=n_contacts).astype(np.float32),
        "bonds/i": rng.integers(0, n, n_bonds).astype(np.int32),
        "bonds/j": rng.integers(0, n, n_bonds).astype(np.int32),
        "bonds/state": np.array([0, 1, 0, 2, 0][:n_bonds], dtype=np.int8),
        "bonds/impulse": rng.normal(size=(n_bonds, 3)),
        "bonds/broken_time": broken_time,
        "bonds/broken_position": broken_position,
        "bonds/history_n": rng.normal(size=n_bonds),
    }


def assert_bit_exact(actual, expected, key=""):
    actual = np.asarray(actual)
    assert actual.dtype == expected.dtype, key
    assert actual.shape == expected.shape, key
    assert actual.tobytes() == expected.tobytes(), key


def temp_files(directory):
    return sorted(p for p in os.listdir(directory) if p.startswith(".") and p.endswith(".tmp"))


# --- round trips ------------------------------------------------------------------------------
def test_frame_round_trip_is_bit_exact_with_schema_attributes(tmp_path):
    path = tmp_path / "states.h5"
    frame = make_frame()
    index = io.append_frame(path, frame, time=0.25, step=250, stage="shear",
                            scenario_text="[sample]\nheight = 0.1\n", tcd_version="9.9",
                            units={"bonds/history_n": "m"})
    assert index == 0
    back = io.read_frame(path, 0)
    assert set(back) == set(frame) | {"time", "step", "stage"}
    for key, value in frame.items():
        assert_bit_exact(back[key], value, key)
    assert (back["time"], back["step"], back["stage"]) == (0.25, 250, "shear")
    with h5py.File(path, "r") as f:
        assert f.attrs["schema_version"] == io.SCHEMA_VERSION == 1
        assert f.attrs["tcd_version"] == "9.9"
        assert f.attrs["scenario"] == "[sample]\nheight = 0.1\n"
        assert "T" in f.attrs["created"]
        group = f["frames/000000"]
        assert group["particles/v"].attrs["units"] == "m/s"
        assert group["particles/w"].attrs["units"] == "rad/s"
        assert group["contacts/impulse"].attrs["units"] == "N s"
        assert group["walls/force"].attrs["units"] == "N"
        assert group["bonds/broken_time"].attrs["units"] == "s"
        assert group["bonds/history_n"].attrs["units"] == "m"
        assert group["particles/layer"].attrs["units"] == "1"


def test_integer_fields_are_stored_with_schema_dtypes(tmp_path):
    path = tmp_path / "states.h5"
    frame = make_frame()
    frame["particles/layer"] = frame["particles/layer"].astype(np.int64)
    frame["bonds/state"] = frame["bonds/state"].astype(np.uint8)
    io.append_frame(path, frame, time=0.0, step=0, stage="pour")
    back = io.read_frame(path)
    assert back["particles/layer"].dtype == np.int32
    assert back["bonds/state"].dtype == np.int8
    np.testing.assert_array_equal(back["particles/layer"], frame["particles/layer"])
    np.testing.assert_array_equal(back["bonds/state"], frame["bonds/state"])


def test_checkpoint_round_trip_is_bit_exact_including_empty_arrays(tmp_path):
    path = tmp_path / "checkpoint.h5"
    rng = np.random.default_rng(3)
    x = rng.normal(size=(11, 3))
    x[2, 1] = nan_with_payload(np.float64)
    arrays = {
        "x": x,
        "w32": rng.normal(size=(11, 3)).astype(np.float32),
        "state": np.array([0, 1, 2, -1], dtype=np.int8),
        "ids": np.array([2**63 + 5, 0], dtype=np.uint64),
        "flags": np.array([True, False, True]),
        "z": np.array([1 + 2j, np.nan], dtype=np.complex128),
        "big_endian": np.arange(4, dtype=">f8"),
        "empty": np.zeros(0),
        "empty_pairs": np.zeros((0, 3), dtype=np.int32),
        "scalar": np.array(0.1),
        "contacts/prev_impulse": rng.normal(size=(5, 3)),
    }
    meta = {"time": 1.5, "step": np.int64(1500), "stage": "shear", "rng": [1, 2, 3],
            "nested": {"nan": float("nan"), "mu": np.float32(0.5)}}
    io.save_checkpoint(path, arrays, meta)
    back, back_meta = io.load_checkpoint(path)
    assert set(back) == set(arrays)
    for key, value in arrays.items():
        assert_bit_exact(back[key], value, key)
    assert back_meta["step"] == 1500 and back_meta["rng"] == [1, 2, 3]
    assert back_meta["stage"] == "shear" and back_meta["nested"]["mu"] == 0.5
    assert np.isnan(back_meta["nested"]["nan"])


def test_appending_keeps_earlier_frames_in_order(tmp_path):
    path = tmp_path / "states.h5"
    frames = [make_frame(n=4 + k, seed=k) for k in range(4)]
    stages = ["pour", "pour", "vibrate", "shear"]
    for k, frame in enumerate(frames):
        assert io.append_frame(path, frame, time=0.1 * k, step=10 * k, stage=stages[k]) == k
        assert io.frame_count(path) == k + 1
    for k, frame in enumerate(frames):
        back = io.read_frame(path, k)
        assert (back["step"], back["stage"]) == (10 * k, stages[k])
        assert_bit_exact(back["particles/x"], frame["particles/x"])
    last = io.read_frame(path, -1)
    assert last["step"] == 30
    assert_bit_exact(last["particles/x"], frames[-1]["particles/x"])
    assert io.read_frame(path, -4)["step"] == 0


def test_series_round_trip_and_csv_twin(tmp_path):
    h5_path, csv_path = tmp_path / "series.h5", tmp_path / "series.csv"
    t = np.linspace(0.0, 1.0, 17)
    series = {"time": t, "force_top": -3.0 * t, "stress": np.stack([t, 2 * t], axis=1),
              "contacts": np.arange(17, dtype=np.int32)}
    io.write_series(h5_path, series, units={"time": "s", "force_top": "N", "stress": "Pa"},
                    attrs={"note": "test", "params": {"a": 1}},
                    csv_path=csv_path, csv_keys=["time", "force_top", "contacts"])
    back = io.read_series(h5_path)
    assert set(back) == set(series)
    for key, value in series.items():
        assert_bit_exact(back[key], value, key)
    with h5py.File(h5_path, "r") as f:
        assert f["force_top"].attrs["units"] == "N" and f["contacts"].attrs["units"] == "1"
        assert json.loads(f.attrs["params"]) == {"a": 1}
    with open(csv_path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["time [s]", "force_top [N]", "contacts [1]"]
    assert len(rows) == 1 + 17
    np.testing.assert_array_equal([float(r[1]) for r in rows[1:]], -3.0 * t)
    assert [int(r[2]) for r in rows[1:]] == list(range(17))


def test_write_json_is_atomic_and_maps_nan_to_null(tmp_path):
    path = tmp_path / "summary.json"
    io.write_json(path, {"a": float("nan"), "b": np.float64(2.5), "c": np.array([1.0, np.inf])})
    assert json.loads(path.read_text()) == {"a": None, "b": 2.5, "c": [1.0, None]}
    assert '\n  "a": null' in path.read_text()
    assert temp_files(tmp_path) == []


# --- crash safety -----------------------------------------------------------------------------
def _write_states(path):
    io.append_frame(path, make_frame(), time=0.0, step=0, stage="pour")


def _write_checkpoint(path):
    io.save_checkpoint(path, {"a": np.arange(3.0), "b": np.ones(4)}, {"step": 1})


def _write_series(path):
    io.write_series(path, {"time": np.arange(5.0), "force": np.ones(5)})


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
@pytest.mark.parametrize("write", [_write_states, _write_checkpoint, _write_series],
                         ids=["append_frame", "save_checkpoint", "write_series"])
def test_write_failing_midway_leaves_previous_file_identical(tmp_path, monkeypatch, write, error):
    path = tmp_path / "out.h5"
    write(path)
    before = path.read_bytes()
    original = h5py.Group.create_dataset
    calls = []

    def create_then_fail(self, *args, **kwargs):
        calls.append(args[0] if args else kwargs.get("name"))
        if len(calls) > 1:
            raise error("disk exploded")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", create_then_fail)
    with pytest.raises(error, match="disk exploded"):
        write(path)
    monkeypatch.undo()
    assert len(calls) == 2
    assert path.read_bytes() == before
    assert temp_files(tmp_path) == []
    assert sorted(os.listdir(tmp_path)) == ["out.h5"]


KILL_CHILD = """
import importlib.util, sys
import numpy as np
spec = importlib.util.spec_from_file_location("tcd_io_child", sys.argv[1])
io = importlib.util.module_from_spec(spec)
spec.loader.exec_module(io)
path, n = sys.argv[2], int(sys.argv[3])
k = io.frame_count(path)
print("ready", flush=True)
while True:
    frame = {"particles/x": np.full((n, 3), float(k)), "particles/v": np.full((n, 3), -1.0),
             "particles/w": np.zeros((n, 3)), "particles/radius": np.full(n, 1e-3),
             "particles/layer": np.zeros(n, dtype=np.int32)}
    io.append_frame(path, frame, time=0.1 * k, step=k, stage="kill")
    k += 1
"""


def test_sigkill_while_appending_never_corrupts_the_target(tmp_path):
    path = tmp_path / "states.h5"
    n = 40_000  # about 3.4 MB per frame, so most of the child's time is spent mid-write
    io.append_frame(path, {"particles/x": np.zeros((n, 3))}, time=0.0, step=0, stage="kill")
    rng = random.Random(7)
    count, leftovers = 1, set()
    for delay in [rng.uniform(0.05, 0.6) for _ in range(5)]:
        child = subprocess.Popen([sys.executable, "-c", KILL_CHILD, IO_SOURCE, str(path), str(n)],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert child.stdout.readline().strip() == "ready", child.stderr.read()
            time.sleep(delay)
            assert child.poll() is None, child.stderr.read()  # still appending when killed
            os.kill(child.pid, signal.SIGKILL)
        finally:
            child.kill()
            child.wait()
            child.stdout.close()
            child.stderr.close()
        new_count = io.frame_count(path)
        assert new_count >= count
        count = new_count
        last = io.read_frame(path, -1)
        assert last["step"] == count - 1
        assert last["particles/x"].shape == (n, 3)
        assert np.all(last["particles/x"] == count - 1)
        for k in range(count):
            assert io.read_frame(path, k)["step"] == k
        leftovers.update(temp_files(tmp_path))
    assert count > 1, "the child never completed an append"
    assert leftovers, "no kill landed mid-write, so nothing was tested"
    assert all(name.startswith(".states.h5.") for name in leftovers)


FULL_DISK_CHILD = """
import importlib.util, os, resource, signal, sys
import numpy as np
spec = importlib.util.spec_from_file_location("tcd_io_child", sys.argv[1])
io = importlib.util.module_from_spec(spec)
spec.loader.exec_module(io)
d = sys.argv[2]
states = os.path.join(d, "states.h5")
io.append_frame(states, {"particles/x": np.zeros((10, 3))}, time=0.0, step=0, stage="s")
io.save_checkpoint(os.path.join(d, "c.h5"), {"x": np.zeros(3)}, {"step": 0})
io.write_series(os.path.join(d, "s.h5"), {"t": np.zeros(3)})
# the disk "fills up" 50 kB past the largest file: writes beyond it fail (EFBIG)
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
limit = max(os.path.getsize(os.path.join(d, f)) for f in os.listdir(d)) + 50000
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
x = np.random.default_rng(1).random((20000, 3))
writes = {"append": lambda: io.append_frame(states, {"particles/x": x}, time=1.0, step=1, stage="s"),
          "checkpoint": lambda: io.save_checkpoint(os.path.join(d, "c.h5"), {"x": x}, {"step": 1}),
          "series": lambda: io.write_series(os.path.join(d, "s.h5"), {"t": x[:, 0]})}
for what, write in writes.items():
    try:
        write()
        print(what, "written")
    except OSError as exc:
        print(what, exc.errno, os.path.basename(exc.filename))
"""


@pytest.mark.skipif(not hasattr(signal, "SIGXFSZ"), reason="needs RLIMIT_FSIZE (POSIX)")
def test_a_full_disk_is_a_plain_oserror_naming_the_file_and_leaves_it_whole(tmp_path):
    """A write that the file system refuses part-way (here a file-size limit: EFBIG, as ENOSPC
    on a full disk) fails with an OSError naming the target, not the temporary, and leaves
    the earlier file whole and no temporary behind. HDF5 writing the file itself failed in its
    close instead: a RuntimeError (so `tcd run` printed a traceback), "Exception ignored"
    noise, and once a segmentation fault (a run on a full tmpfs, session 70)."""
    import errno
    child = subprocess.run([sys.executable, "-c", FULL_DISK_CHILD, IO_SOURCE, str(tmp_path)],
                           capture_output=True, text=True, timeout=120)
    assert child.returncode == 0, child.stderr
    assert child.stdout.split("\n")[:3] == [f"append {errno.EFBIG} states.h5",
                                             f"checkpoint {errno.EFBIG} c.h5",
                                             f"series {errno.EFBIG} s.h5"], child.stdout
    assert "Exception ignored" not in child.stderr and "Traceback" not in child.stderr, child.stderr
    assert sorted(os.listdir(tmp_path)) == ["c.h5", "s.h5", "states.h5"]
    assert io.frame_count(tmp_path / "states.h5") == 1
    assert io.load_checkpoint(tmp_path / "c.h5")[1] == {"step": 0}
    assert np.array_equal(io.read_series(tmp_path / "s.h5")["t"], np.zeros(3))


def test_files_past_the_in_memory_size_are_written_by_hdf5_once_the_disk_holds_them(
        tmp_path, monkeypatch):
    """Above io.IN_MEMORY_BYTES the files are written by HDF5 on the disk (what would be
    held three times in memory): the same contents; and where the free space is short, an
    OSError (ENOSPC) naming the target before a byte is written."""
    import errno
    import shutil
    a, b = tmp_path / "a", tmp_path / "b"
    for folder, limit in ((a, io.IN_MEMORY_BYTES), (b, 0)):
        folder.mkdir()
        monkeypatch.setattr(io, "IN_MEMORY_BYTES", limit)
        for k in range(3):
            io.append_frame(folder / "states.h5", make_frame(seed=k), time=0.1 * k, step=k,
                            stage="pour")
        assert io.keep_frames(folder / "states.h5", 2) == 1
        _write_checkpoint(folder / "c.h5")
        _write_series(folder / "s.h5")
    for k in range(2):
        fa, fb = io.read_frame(a / "states.h5", k), io.read_frame(b / "states.h5", k)
        assert fa.keys() == fb.keys()
        assert all(np.array_equal(fa[key], fb[key], equal_nan=np.asarray(fa[key]).dtype.kind == "f")
                   for key in fa)
    assert io.frame_count(b / "states.h5") == 2
    ca, cb = io.load_checkpoint(a / "c.h5"), io.load_checkpoint(b / "c.h5")
    assert ca[1] == cb[1] and all(np.array_equal(ca[0][k], cb[0][k]) for k in ca[0])
    sa, sb = io.read_series(a / "s.h5"), io.read_series(b / "s.h5")
    assert all(np.array_equal(sa[k], sb[k]) for k in sa)
    before = (b / "states.h5").read_bytes()
    monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10**12, 10**12, 0))
    with pytest.raises(OSError) as caught:
        io.append_frame(b / "states.h5", make_frame(seed=9), time=1.0, step=9, stage="pour")
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(b / "states.h5")
    assert (b / "states.h5").read_bytes() == before and temp_files(b) == []

def test_atomic_path_removes_temp_on_error_and_replaces_on_success(tmp_path):
    path = tmp_path / "data.txt"
    path.write_text("old")
    with pytest.raises(ZeroDivisionError):
        with io.atomic_path(path) as tmp:
            assert os.path.dirname(tmp) == str(tmp_path)
            with open(tmp, "w") as fh:
                fh.write("half")
            1 / 0
    assert path.read_text() == "old" and temp_files(tmp_path) == []
    with io.atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            fh.write("new")
    assert path.read_text() == "new" and temp_files(tmp_path) == []


# --- errors -----------------------------------------------------------------------------------
@pytest.mark.parametrize("read", [io.read_frame, io.frame_count, io.read_series,
                                  io.load_checkpoint, io.info])
def test_missing_file_is_reported_with_its_path(tmp_path, read):
    path = tmp_path / "nope.h5"
    with pytest.raises(FileNotFoundError, match="nope.h5"):
        read(path)


def test_not_hdf5_file_is_a_value_error_naming_the_path(tmp_path):
    path = tmp_path / "notes.h5"
    path.write_text("this is not HDF5")
    with pytest.raises(ValueError, match=r"notes\.h5.*not an HDF5 file"):
        io.read_frame(path)
    with pytest.raises(ValueError, match=r"notes\.h5"):
        io.append_frame(path, make_frame(), time=0.0, step=0, stage="pour")
    assert path.read_text() == "this is not HDF5"


@pytest.mark.parametrize("version", [2, None])
def test_unknown_or_missing_schema_version_is_a_value_error(tmp_path, version):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f.create_group("frames")
        if version is not None:
            f.attrs["schema_version"] = version
    with pytest.raises(ValueError, match=r"other\.h5.*schema_version"):
        io.frame_count(path)
    with pytest.raises(ValueError, match=r"other\.h5.*schema_version"):
        io.info(path)


def test_wrong_kind_of_tcd_file_is_a_value_error(tmp_path):
    path = tmp_path / "series.h5"
    io.write_series(path, {"time": np.arange(3.0)})
    with pytest.raises(ValueError, match=r"series\.h5.*series file, expected a states file"):
        io.read_frame(path)


def test_frame_index_out_of_range_names_path_index_and_count(tmp_path):
    path = tmp_path / "states.h5"
    _write_states(path)
    _write_states(path)
    with pytest.raises(IndexError, match=r"states\.h5.*index 2 .*2 frames"):
        io.read_frame(path, 2)
    with pytest.raises(IndexError, match=r"index -3 .*2 frames"):
        io.read_frame(path, -3)


def _replace(key, value):
    def edit(frame):
        frame[key] = value
    return edit


def _drop(key):
    def edit(frame):
        del frame[key]
    return edit


@pytest.mark.parametrize("edit, key", [
    (_replace("particles/x", np.zeros((7, 2))), "particles/x"),
    (_replace("particles/radius", np.ones(6)), "particles/radius"),
    (_replace("particles/v", np.zeros((8, 3))), "particles/v"),
    (_replace("particles/layer", np.zeros(7)), "particles/layer"),
    (_replace("particles/x", np.zeros((7, 3), dtype=np.int64)), "particles/x"),
    (_replace("walls/extent", np.zeros((3, 3))), "walls/extent"),
    (_replace("walls/force", np.zeros((2, 3))), "walls/force"),
    (_replace("contacts/gap", np.zeros(8)), "contacts/gap"),
    (_replace("contacts/j", np.full(9, 10, dtype=np.int32)), "contacts/j"),
    (_replace("bonds/state", np.full(5, 3, dtype=np.int8)), "bonds/state"),
    (_replace("bonds/history_n", np.zeros(4)), "bonds/history_n"),
    (_replace("notagroup", np.zeros(3)), "notagroup"),
    (_replace("particles/name", np.array(["a"] * 7)), "particles/name"),
    (_drop("particles/x"), "particles/x"),
])
def test_inconsistent_frame_is_rejected_before_touching_disk(tmp_path, edit, key):
    path = tmp_path / "states.h5"
    frame = make_frame()
    edit(frame)
    with pytest.raises(ValueError, match=re.escape(repr(key))):
        io.append_frame(path, frame, time=0.0, step=0, stage="pour")
    assert os.listdir(tmp_path) == []


def test_inconsistent_series_is_rejected_naming_the_key(tmp_path):
    with pytest.raises(ValueError, match="'force'"):
        io.write_series(tmp_path / "s.h5", {"time": np.arange(4.0), "force": np.arange(3.0)})
    with pytest.raises(ValueError, match="'stress'"):
        io.write_series(tmp_path / "s.h5", {"stress": np.zeros((4, 2))},
                        csv_path=tmp_path / "s.csv", csv_keys=["stress"])
    assert os.listdir(tmp_path) == []


# --- summaries --------------------------------------------------------------------------------
def test_info_summarises_states_series_and_checkpoints(tmp_path):
    states = tmp_path / "states.h5"
    for k, stage in enumerate(["pour", "shear", "shear"]):
        io.append_frame(states, make_frame(), time=0.5 * k, step=k, stage=stage,
                        scenario_text="a = 1\nb = 2\n", tcd_version="0.1.0")
    text = io.info(states)
    assert "states" in text and "schema_version 1" in text and "tcd_version 0.1.0" in text
    assert "frames: 3" in text and "time 0 .. 1 s" in text
    assert "stages: pour, shear" in text
    assert "7 particles" in text and "9 contacts" in text
    assert "intact 3" in text and "broken in tension 1" in text and "broken in shear 1" in text

    series = tmp_path / "series.h5"
    samples = {"time": np.array([0.0, 0.5, 1.0]), "force": np.array([3.0, -1.0, 2.0])}
    io.write_series(series, samples, units={"time": "s", "force": "N"})
    text = io.info(series)
    assert "series: 2 keys" in text
    assert "force [N]: length 3, min -1, max 3, last 2" in text
    assert "time [s]: length 3" in text

    checkpoint = tmp_path / "checkpoint.h5"
    io.save_checkpoint(checkpoint, {"x": np.zeros((4, 3))}, {"step": 4})
    text = io.info(checkpoint)
    assert "checkpoint" in text and "x: float64 (4, 3)" in text and "step" in text
    assert "sample (grains" not in text           # not grains in a mould: no sample section


def test_info_reads_a_prepared_sample_from_its_arrays(tmp_path):
    """Grains in a mould (a cylinder between two plates): `tcd info` gives the sample's size,
    packing and courses from the arrays alone. Two columns of spheres of known sizes."""
    from tcd.walls import CYLINDER, PLANE
    r = np.array([0.002, 0.002, 0.001, 0.001, 0.001])
    z = np.array([0.002, 0.006, 0.009, 0.011, 0.013])           # two courses, touching
    x = np.column_stack([np.array([0.0, 0.0, 0.003, 0.003, 0.003]), np.zeros(5), z])
    layer = np.array([0, 0, 1, 1, 1], np.int32)
    R, H = 0.01, 0.015
    arrays = {"particles/x": x, "particles/radius": r, "particles/layer": layer,
              "walls/kind": np.array([PLANE, CYLINDER, PLANE], np.int32),
              "walls/point": np.array([[0, 0, 0], [0, 0, 0], [0, 0, H]], float),
              "walls/direction": np.array([[0, 0, 1], [0, 0, 1], [0, 0, -1]], float),
              "walls/radius": np.array([R, R, R]),
              "walls/force": np.array([[0, 0, -0.5], [0, 0, 0], [0, 0, 0.25]]),
              "contacts/gap": np.array([0.0, -4e-6, 0.0]), "contacts/j": np.array([1, 3, 5], np.int32)}
    path = tmp_path / "prepared.h5"
    io.save_checkpoint(path, arrays, {"time": 1.0})
    text = io.info(path)
    solid = float(np.sum(4 / 3 * np.pi * r**3))
    assert "5 particles (2 + 3 in courses [0, 1]), diameters 2 to 4 mm" in text
    assert "mould: diameter 20.0 mm, plates at 0.0 and 15.0 mm (force of the grains on the top plate 0.25 N)" in text
    assert f"packing between the plates {solid / (np.pi * R**2 * H):.3f}" in text
    assert f"highest grain top 14.0 mm (1.0 mm below the top plate), packing below it {solid / (np.pi * R**2 * 0.014):.3f}" in text
    assert "courses by their highest grain 8.0 / 6.0 mm" in text
    assert "outside the mould: 0" in text
    # two particle contacts (partners below n = 5), one with the wall; 4 um of overlap over 2 mm
    assert "contacts: 3, coordination 0.80, largest overlap 0.20 % of the smallest diameter" in text
    # with their pairs and impulses: the one pressed pair (0-1, pushed apart along +z) of the two
    arrays.update({"contacts/i": np.array([0, 2, 4], np.int32),
                   "contacts/impulse": np.array([[0, 0, 1e-5], [0, 0, 0], [0, 0, 1e-5]])})
    io.save_checkpoint(path, arrays, {"time": 1.0})
    assert "contacts: 3, coordination 0.80 (0.40 carrying a force), largest" in io.info(path)
    # a grain through the mould (about its axis), one through the top plate
    arrays["particles/x"] = x + np.array([[0.0085, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0.0015]])
    io.save_checkpoint(path, arrays, {"time": 1.0})
    assert "outside the mould: 2 " in io.info(path)
    arrays["walls/point"][1] = [-0.0085, 0, 0]               # the mould moved away: all out
    io.save_checkpoint(path, arrays, {"time": 1.0})
    assert "outside the mould: 5 " in io.info(path)
    arrays["particles/x"], arrays["walls/point"][1] = x, [0, 0, 0]
    # the top plate lowered onto the highest grain; a second cylinder (two rings): no section
    arrays["walls/point"][2, 2] = 0.014
    io.save_checkpoint(path, arrays, {"time": 1.0})
    assert "highest grain top 14.0 mm (at the top plate)" in io.info(path)
    arrays["walls/kind"][0] = CYLINDER
    io.save_checkpoint(path, arrays, {"time": 1.0})
    assert "sample (grains" not in io.info(path)


@pytest.mark.parametrize("kind", ["checkpoint", "series"])
def test_a_byte_damaged_on_disk_is_a_read_error_not_wrong_numbers(tmp_path, kind):
    """Numeric datasets carry HDF5's Fletcher-32 checksum: flipping one byte of the stored
    numbers makes the read fail (before, h5py returned the damaged values)."""
    path = tmp_path / f"{kind}.h5"
    values = np.linspace(0.0, 1.0, 20000)
    if kind == "checkpoint":
        io.save_checkpoint(path, {"x": values}, {"time": 0.0})
        name = "arrays/x"
    else:
        io.write_series(path, {"time": values})
        name = "time"
    with h5py.File(path, "r") as f:
        ds = f[name]
        assert ds.fletcher32
        offset = ds.id.get_chunk_info(0).byte_offset
    data = bytearray(path.read_bytes())
    data[offset + 100] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(OSError, match="checksum mismatch, the file is damaged"):
        if kind == "checkpoint":
            io.load_checkpoint(path)
        else:
            io.read_series(path)


def test_states_read_back_are_checked_before_anything_indexes_with_them(tmp_path):
    """A file edited or damaged outside tcd (a short radius array, a contact index past the
    particles, radii stored as text, a negative radius, a NaN position) gave IndexErrors or
    NumPy broadcasting errors deep inside `tcd info`, `export` and `analyse`."""
    f = make_frame()
    io.check_state(f, "ok")                               # as written: fine
    n = len(f["particles/x"])
    bad = {
        "short radius": ({"particles/radius": f["particles/radius"][:3]},
                         "key 'particles/radius' has length 3 but 'particles/x' has 7"),
        "index": ({"contacts/i": f["contacts/i"] + n}, "key 'contacts/i' has indices in"),
        "text radius": ({"particles/radius": np.array([b"a"] * n)}, "has dtype |S1"),
        "negative": ({"particles/radius": -f["particles/radius"]}, "7 radii that are not positive"),
        "nan x": ({"particles/x": np.where(np.arange(n)[:, None] == 2, np.nan, f["particles/x"])},
                  "1 positions that are not finite"),
    }
    for name, (change, message) in bad.items():
        with pytest.raises(ValueError, match=re.escape(message)):
            io.check_state({**f, **change}, f"file.h5 ({name})")
    io.check_state({**f, **bad["nan x"][0]}, "diverged", finite_positions=False)
    # a checkpoint keeps its walls in its meta: wall_slots says how many contacts may touch
    no_walls = {k: v for k, v in f.items() if not k.startswith("walls/")}
    io.check_state(no_walls, "ckpt", wall_slots=3)
    with pytest.raises(ValueError, match=r"expected \[0, 8\) with N=7, W=1"):
        io.check_state({**no_walls, "contacts/j": np.array([0, 9] * 4 + [0], np.int32)}, "ckpt",
                       wall_slots=1)
    # tcd info still lists such a checkpoint's arrays, and says why it shows no sample
    path = tmp_path / "damaged.h5"
    io.save_checkpoint(path, {**f, "particles/radius": f["particles/radius"][:3]}, {"time": 0.0})
    text = io.info(path)
    assert "particles/radius: float64 (3,)" in text
    assert "sample: not read (arrays: key 'particles/radius' has length 3" in text


def test_unreadable_meta_and_schema_are_named_with_the_file(tmp_path):
    path = tmp_path / "c.h5"
    io.save_checkpoint(path, {"particles/x": np.zeros((1, 3))}, {"time": 0.0})
    with h5py.File(path, "a") as f:
        f.attrs["meta"] = "{time: 0"
    with pytest.raises(ValueError, match=re.escape(f"{path}: its 'meta' attribute is not valid JSON")):
        io.load_checkpoint(path)
    for version, shown in ((2, "2"), ("two", "'two'")):
        with h5py.File(path, "a") as f:
            f.attrs["schema_version"] = version
        with pytest.raises(ValueError, match=re.escape(f"{path}: unknown schema_version {shown} ")):
            io.load_checkpoint(path)


def test_atomic_path_onto_a_directory_fails_before_the_work(tmp_path):
    (tmp_path / "out.h5").mkdir()
    with pytest.raises(IsADirectoryError, match="is a directory, not a file"):
        with io.atomic_path(tmp_path / "out.h5"):
            pytest.fail("the body ran")
    assert [p.name for p in tmp_path.iterdir()] == ["out.h5"]       # no temporary file left


def test_an_output_that_cannot_be_created_is_named_by_its_path_not_the_temporary(tmp_path):
    """A write into a folder that does not exist named the temporary file beside the target
    ('.c.h5.n3jwrbzf.tmp'), not the path given (session 42 API audit)."""
    target = tmp_path / "no" / "such" / "c.h5"
    with pytest.raises(FileNotFoundError) as caught:
        io.save_checkpoint(target, {"a": np.zeros(2)}, {})
    assert caught.value.filename == str(target) and ".tmp" not in str(caught.value)


# --- session 43's mutation audit of the files and checks that guard the results -------------
def _frame(n=3):
    return {"particles/x": np.arange(3.0 * n).reshape(n, 3), "particles/radius": np.full(n, 1e-3)}


# io.py atomic_path: fsync of the temporary before os.replace, then of the directory
def test_atomic_write_fsyncs_the_new_content_before_renaming_it(tmp_path, monkeypatch):
    events = []
    real_file, real_dir, real_replace = io._fsync_file, io._fsync_dir, os.replace

    def fsync_file(path):
        with open(path) as fh:
            events.append(("fsync", os.fspath(path), fh.read()))
        real_file(path)

    def fsync_dir(directory):
        events.append(("fsync_dir", os.fspath(directory)))
        real_dir(directory)

    def replace(src, dst):
        events.append(("replace", os.fspath(src), os.fspath(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(io, "_fsync_file", fsync_file)
    monkeypatch.setattr(io, "_fsync_dir", fsync_dir)
    monkeypatch.setattr(os, "replace", replace)
    target = tmp_path / "summary.json"
    io.write_json(target, {"a": 1})
    assert [e[0] for e in events] == ["fsync", "replace", "fsync_dir"], events
    (_, synced, content), (_, src, dst), (_, directory) = events
    assert synced == src != str(target) and dst == str(target)   # the temporary, then renamed
    assert content == target.read_text() == '{\n  "a": 1\n}\n'
    assert directory == str(tmp_path)


# io.py atomic_path: the result keeps the mode of the file it replaces (umask for a new one)
def test_atomic_write_gives_the_result_the_replaced_file_s_mode_or_the_umask_s(tmp_path,
                                                                              monkeypatch):
    """The umask at the time of the write, not the caller's when tcd was imported (002 for a
    user of Debian or Ubuntu, 077 on a hardened machine: session 74's review)."""
    live = pathlib.Path("/proc/self/status").exists()
    if not live:                                        # elsewhere: the umask at import
        monkeypatch.setattr(io, "_umask", 0o022)
    old = os.umask(0o077)
    try:
        io.write_json(tmp_path / "private.json", {"a": 0})
        if live:
            assert stat.S_IMODE(os.stat(tmp_path / "private.json").st_mode) == 0o600
        os.umask(0o022)
        target = tmp_path / "summary.json"
        io.write_json(target, {"a": 1})                  # mkstemp alone would give 0o600
        assert stat.S_IMODE(os.stat(target).st_mode) == 0o644
        os.chmod(target, 0o640)
        io.write_json(target, {"a": 2})
        assert stat.S_IMODE(os.stat(target).st_mode) == 0o640
        states = tmp_path / "states.h5"
        io.append_frame(states, _frame(), time=0.0, step=0, stage="prepare")
        assert stat.S_IMODE(os.stat(states).st_mode) == 0o644
    finally:
        os.umask(old)


# io.py keep_frames: the cut file keeps the root attributes (scenario text, version, schema)
# and every kept frame whole (attributes, datasets, units)
def test_keep_frames_keeps_the_file_attributes_and_the_kept_frames_whole(tmp_path):
    path = tmp_path / "states.h5"
    text = 'name = "t"\n[solver]\ntime_step = 0.001\n'
    for k in range(4):
        io.append_frame(path, _frame(), time=0.1 * k, step=10 * k, stage="shear",
                        scenario_text=text, tcd_version="9.9")
    with h5py.File(path, "r") as f:
        before = {k: v for k, v in f.attrs.items()}
    assert io.keep_frames(path, 2) == 2
    assert io.frame_count(path) == 2
    with h5py.File(path, "r") as f:
        after = {k: v for k, v in f.attrs.items()}
        assert f["frames/000001/particles/x"].attrs["units"] == "m"
    assert after == before and after["scenario"] == text and after["tcd_version"] == "9.9"
    back = io.read_frame(path, -1)
    assert (back["time"], back["step"], back["stage"]) == (0.1, 10, "shear")
    np.testing.assert_array_equal(back["particles/x"], _frame()["particles/x"])
    # the export reads the time step back from the cut file's scenario
    from tcd import export
    assert export.load_states(path)[1] == 0.001


# io.py check_state: a zero radius is not a grain (inverse mass, volume, glyph scale all break)
def test_a_zero_radius_read_back_is_refused_naming_the_key():
    frame = _frame()
    frame["particles/radius"] = np.array([1e-3, 0.0, 1e-3])
    with pytest.raises(ValueError, match=r"where: key 'particles/radius' holds 1 radii that are not positive"):
        io.check_state(frame, "where")


# io.py _to_int: an integer that does not fit the schema dtype is refused, not wrapped on disk
def test_integers_outside_the_schema_dtype_are_refused_not_wrapped(tmp_path):
    path = tmp_path / "states.h5"
    for key, value in (("particles/layer", np.array([0, 1, 2**31], np.int64)),
                       ("bonds/state", np.array([0, 256 + 1], np.int64))):
        frame = _frame()
        frame[key] = value
        if key.startswith("bonds/"):
            frame.update({"bonds/i": np.array([0, 1], np.int32), "bonds/j": np.array([1, 2], np.int32)})
        with pytest.raises(ValueError, match=rf"'{key}' has values outside the int(32|8) range"):
            io.append_frame(path, frame, time=0.0, step=0, stage="prepare")
    assert os.listdir(tmp_path) == []


# io.py _check_frame: units that contradict the schema (mm for positions) are refused
def test_units_that_contradict_the_schema_are_refused_before_writing(tmp_path):
    path = tmp_path / "states.h5"
    with pytest.raises(ValueError, match=r"units 'mm' for 'particles/x' contradict the schema \('m'\)"):
        io.append_frame(path, _frame(), time=0.0, step=0, stage="prepare",
                        units={"particles/x": "mm"})
    assert not path.exists()


# io.py _write_frame: every frame records the unit of its time attribute
def test_each_frame_records_its_time_unit(tmp_path):
    path = tmp_path / "states.h5"
    for k in range(2):
        io.append_frame(path, _frame(), time=0.5 * k, step=k, stage="prepare")
    with h5py.File(path, "r") as f:
        assert [f["frames"][name].attrs["time_units"] for name in ("000000", "000001")] == ["s", "s"]



def test_source_date_epoch_fixes_the_files_creation_time(tmp_path, monkeypatch):
    """The `created` attribute made every file of two identical runs differ in its bytes
    (the determinism audit of session 48); SOURCE_DATE_EPOCH fixes it, as reproducible builds
    do, and a malformed one is refused by name."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    paths = [tmp_path / "a.h5", tmp_path / "b.h5"]
    for k, path in enumerate(paths):
        if k:
            time.sleep(1.05)        # another second on the clock
        io.save_checkpoint(path, {"x": np.arange(4.0)}, {"step": 3})
    with h5py.File(paths[0], "r") as f:
        assert f.attrs["created"] == "2023-11-14T22:13:20+00:00"
    assert paths[0].read_bytes() == paths[1].read_bytes()
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    with pytest.raises(ValueError, match="SOURCE_DATE_EPOCH='yesterday': expected whole seconds"):
        io.save_checkpoint(tmp_path / "c.h5", {"x": np.arange(4.0)}, {"step": 3})
    assert not (tmp_path / "c.h5").exists()


def test_a_malformed_source_date_epoch_is_refused_before_a_command_runs(tmp_path, monkeypatch,
                                                                        capsys):
    from tcd import cli
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "soon")
    assert cli.main(["info", str(tmp_path / "none.h5")]) == 2
    assert "SOURCE_DATE_EPOCH='soon': expected whole seconds" in capsys.readouterr().err


def test_a_series_and_its_csv_twin_are_replaced_together_or_not_at_all(tmp_path, monkeypatch):
    """The .h5 was replaced before the .csv was written: a disk that filled at the CSV left
    the new .h5 beside the old .csv (or none), a pair that disagree (`tcd analyse`, session
    72's review). Now the CSV is written first and both stay as they were."""
    import errno
    h5, csv_path = tmp_path / "a.h5", tmp_path / "a.csv"
    io.write_series(h5, {"time": np.arange(3.0)}, csv_path=csv_path)
    before = h5.read_bytes(), csv_path.read_bytes()
    real = io._csv_cell

    def full(value):
        if value == 4.0:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(value)
    monkeypatch.setattr(io, "_csv_cell", full)
    with pytest.raises(OSError) as caught:
        io.write_series(h5, {"time": np.arange(6.0)}, csv_path=csv_path)
    assert caught.value.filename == str(csv_path)
    assert (h5.read_bytes(), csv_path.read_bytes()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "a.h5"]
    monkeypatch.undo()
    io.write_series(h5, {"time": np.arange(6.0)}, csv_path=csv_path)
    assert list(io.read_series(h5)["time"]) == list(range(6))
    assert csv_path.read_text().count("\n") == 7
