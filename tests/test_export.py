"""`tcd export`: states, prepared samples and checkpoints to VTK (.vtu per part and frame, .pvd
time series). The files are read back with meshio (and parsed as XML where meshio's reader does
not cope: an empty cell block) and compared with the arrays they came from."""
import math
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

from tcd import cli, export, io

H = 1e-3
SCENARIO = f'name = "t"\n[solver]\ntime_step = {H}\n'


def frame(shift=0.0, bonds_state=(0, 1)):
    """Three spheres along x touching in a row, a fourth apart; a floor and a mould."""
    x = np.array([[0.0, 0, 0.01], [0.02, 0, 0.01], [0.04, 0, 0.01], [0.0, 0.03, 0.01]]) + shift
    return {
        "particles/x": x,
        "particles/v": np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 0], [3.0, 4.0, 0]]),
        "particles/w": np.zeros((4, 3)),
        "particles/radius": np.array([0.01, 0.01, 0.01, 0.005]),
        "particles/layer": np.array([0, 0, 1, 1], np.int32),
        "walls/kind": np.array([io.WALL_PLANE, io.WALL_CYLINDER], np.int32),
        "walls/point": np.zeros((2, 3)),
        "walls/direction": np.array([[0, 0, 1.0], [0, 0, 1.0]]),
        "walls/radius": np.array([0.05, 0.06]),
        "walls/extent": np.array([[0.0, 0.0], [0.0, 0.1]]),
        "walls/force": np.array([[0, 0, -7.0], [1.0, 0, 0]]),
        # contact 0-1 (compressive 2 N s along x, 1 N s tangent), 1-2, and 2 with wall 0 (j = N)
        "contacts/i": np.array([0, 1, 2], np.int32),
        "contacts/j": np.array([1, 2, 4], np.int32),
        "contacts/impulse": np.array([[2.0, 1.0, 0], [-0.5, 0, 0], [0, 0, 9.0]]),
        "contacts/gap": np.array([0.0, -1e-6, 0.0]),
        "bonds/i": np.array([0, 1], np.int32),
        "bonds/j": np.array([3, 2], np.int32),
        "bonds/state": np.array(bonds_state, np.int8),
        "bonds/impulse": np.array([[0, 3.0, 0], [1.0, 0, 0]]),
    }


@pytest.fixture
def states(tmp_path):
    path = tmp_path / "states.h5"
    io.append_frame(path, frame(), time=0.5, step=10, stage="prepare", scenario_text=SCENARIO)
    io.append_frame(path, frame(0.001, (2, 0)), time=0.75, step=20, stage="shear")
    return path


def test_particles_are_points_with_their_arrays(states, tmp_path):
    written = export.export(states, tmp_path / "vtk")
    assert [w.name for w in written[-4:]] == [f"states_{p}.pvd" for p in export.PARTS]
    f = frame()
    m = meshio.read(tmp_path / "vtk" / "states_particles_000000.vtu")
    np.testing.assert_array_equal(m.points, f["particles/x"])
    np.testing.assert_array_equal(m.cells_dict["vertex"].ravel(), np.arange(4))
    np.testing.assert_array_equal(m.point_data["radius"], f["particles/radius"])
    np.testing.assert_array_equal(m.point_data["diameter"], 2 * f["particles/radius"])
    np.testing.assert_array_equal(m.point_data["velocity"], f["particles/v"])
    np.testing.assert_allclose(m.point_data["speed"], [1.0, 2.0, 0.0, 5.0])
    np.testing.assert_array_equal(m.point_data["layer"], [0, 0, 1, 1])
    second = meshio.read(tmp_path / "vtk" / "states_particles_000001.vtu")
    np.testing.assert_array_equal(second.points, f["particles/x"] + 0.001)


def test_contacts_are_lines_between_particles_with_normal_and_tangential_impulse(states, tmp_path):
    export.export(states, tmp_path / "vtk", frames=[0])
    m = meshio.read(tmp_path / "vtk" / "states_contacts_000000.vtu")
    # the contact with the floor (j = N) is not a line
    np.testing.assert_array_equal(m.cells_dict["line"], [[0, 1], [1, 2]])
    cd = {k: v[0] for k, v in m.cell_data.items()}
    np.testing.assert_allclose(cd["normal_impulse"], [2.0, -0.5])
    np.testing.assert_allclose(cd["tangential_impulse"], [1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(cd["normal_force"], [2.0 / H, -0.5 / H])
    np.testing.assert_array_equal(cd["gap"], [0.0, -1e-6])
    np.testing.assert_array_equal(cd["impulse"], frame()["contacts/impulse"][:2])


def test_bonds_carry_state_and_impulse_per_frame(states, tmp_path):
    export.export(states, tmp_path / "vtk")
    for k, state in ((0, [0, 1]), (1, [2, 0])):
        m = meshio.read(tmp_path / "vtk" / f"states_bonds_{k:06d}.vtu")
        np.testing.assert_array_equal(m.cells_dict["line"], [[0, 3], [1, 2]])
        np.testing.assert_array_equal(m.cell_data["state"][0], state)
        np.testing.assert_array_equal(m.cell_data["intact"][0], [s == 0 for s in state])
    # bond 0-3 lies along y, its impulse (0, 3, 0) is all normal; bond 1-2 along x
    np.testing.assert_allclose(m.cell_data["normal_impulse"][0], [3.0, 1.0])
    np.testing.assert_allclose(m.cell_data["tangential_impulse"][0], [0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(m.cell_data["normal_force"][0], [3.0 / H, 1.0 / H])


def test_walls_are_a_disc_and_a_cylinder_shell_with_their_forces(states, tmp_path):
    export.export(states, tmp_path / "vtk", frames=[-1], parts=["walls"])
    m = meshio.read(tmp_path / "vtk" / "states_walls_000001.vtu")
    tri = m.cells_dict["triangle"]
    wall = m.cell_data["wall"][0]
    s = export.WALL_SEGMENTS
    assert np.count_nonzero(wall == 0) == s and np.count_nonzero(wall == 1) == 2 * s
    disc = m.points[np.unique(tri[wall == 0])]
    assert np.all(np.abs(disc[:, 2]) < 1e-15)
    assert np.max(np.hypot(disc[:, 0], disc[:, 1])) == pytest.approx(0.05, rel=1e-12)
    shell = m.points[np.unique(tri[wall == 1])]
    np.testing.assert_allclose(np.hypot(shell[:, 0], shell[:, 1]), 0.06, rtol=1e-12)
    assert sorted(set(np.round(shell[:, 2], 12))) == [0.0, 0.1]
    # the shell's area is close to the cylinder's (inscribed polygon)
    a, b, c = (m.points[tri[wall == 1][:, q]] for q in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    assert area == pytest.approx(2 * math.pi * 0.06 * 0.1, rel=2e-3)
    np.testing.assert_array_equal(m.cell_data["force"][0][wall == 0], np.tile([0, 0, -7.0], (s, 1)))
    np.testing.assert_array_equal(m.cell_data["kind"][0][wall == 1], io.WALL_CYLINDER)
    # each wall's force once, as field data: summing the cells' copies gives a multiple
    np.testing.assert_array_equal(m.field_data["wall_force"], frame()["walls/force"])


def test_collections_list_the_frames_with_their_times(states, tmp_path):
    export.export(states, tmp_path / "vtk", frames=[1, 0])
    root = ET.parse(tmp_path / "vtk" / "states_particles.pvd").getroot()
    assert root.get("type") == "Collection"
    rows = [(float(d.get("timestep")), d.get("file")) for d in root.iter("DataSet")]
    assert rows == [(0.75, "states_particles_000001.vtu"), (0.5, "states_particles_000000.vtu")]
    for _, name in rows:
        assert (tmp_path / "vtk" / name).is_file()


def test_frames_at_one_time_are_listed_once_the_later(tmp_path):
    """The end of a preparation and the start of its shear (before and after the bonding)
    share a time: a .pvd reader shows the first dataset listed at a time, so the collection
    lists the later one only (the state the run goes on from); both frames' files are written."""
    path = tmp_path / "states.h5"
    io.append_frame(path, frame(bonds_state=(0, 0)), time=0.5, step=10, stage="prepare",
                    scenario_text=SCENARIO)
    io.append_frame(path, frame(bonds_state=(0, 0)), time=0.5, step=10, stage="shear")
    io.append_frame(path, frame(0.001, (2, 0)), time=0.75, step=20, stage="shear")
    export.export(path, tmp_path / "vtk")
    for part in export.PARTS:
        root = ET.parse(tmp_path / "vtk" / f"states_{part}.pvd").getroot()
        rows = [(float(d.get("timestep")), d.get("file")) for d in root.iter("DataSet")]
        assert rows == [(0.5, f"states_{part}_000001.vtu"), (0.75, f"states_{part}_000002.vtu")]
        assert all((tmp_path / "vtk" / f"states_{part}_{k:06d}.vtu").is_file() for k in range(3))
    assert export._one_per_time([(0.0, "a"), (0.1, "b"), (0.1, "c"), (0.0, "d")]) == [
        (0.0, "a"), (0.1, "c"), (0.0, "d")]        # frames asked for in another order: kept


def test_sigterm_stops_an_export_without_a_temporary_left(states, tmp_path):
    """SIGTERM (`kill`, `timeout`, a scheduler) stops `tcd export` as Ctrl-C does: exit 130,
    the file being written removed, the files written before whole (it used to kill the
    process and leave a `.NAME.tmp` among the outputs)."""
    import subprocess
    import sys
    out = tmp_path / "vtk"
    script = f"""
import os, signal, sys
import meshio
from tcd import cli
real, calls = meshio.write, [0]
def write(path, mesh, **kw):
    calls[0] += 1
    real(path, mesh, **kw)
    if calls[0] == 3:           # the third file written into its temporary, then the signal
        os.kill(os.getpid(), signal.SIGTERM)
meshio.write = write
sys.exit(cli.main(["export", {str(states)!r}, "--out", {str(out)!r}]))
"""
    from conftest import default_stop_signals
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, preexec_fn=default_stop_signals)
    assert proc.returncode == cli.EXIT_INTERRUPTED, (proc.returncode, proc.stderr)
    assert "interrupted" in proc.stderr
    names = sorted(p.name for p in out.iterdir())
    assert names == ["states_contacts_000000.vtu", "states_particles_000000.vtu"], names


def test_an_empty_part_is_a_valid_file_without_cells(tmp_path):
    path = tmp_path / "states.h5"
    f = {k: v for k, v in frame().items() if not k.startswith("bonds/")}
    io.append_frame(path, f, time=0.0, step=0, stage="prepare")
    export.export(path, tmp_path / "vtk", parts=["bonds"])
    piece = ET.parse(tmp_path / "vtk" / "states_bonds_000000.vtu").getroot().find(".//Piece")
    assert piece.get("NumberOfCells") == "0" and piece.get("NumberOfPoints") == "4"
    # no scenario, no time step: impulses only, no forces
    export.export(path, tmp_path / "vtk", parts=["contacts"])
    m = meshio.read(tmp_path / "vtk" / "states_contacts_000000.vtu")
    assert "normal_impulse" in m.cell_data and "normal_force" not in m.cell_data


def test_a_prepared_sample_or_checkpoint_exports_its_one_state(tmp_path):
    f = frame()
    arrays = {k: v for k, v in f.items()}
    arrays["particles/inv_mass"] = np.ones(4)
    arrays["contacts/start"] = np.array([0, 1, 2, 3, 3], np.int32)
    arrays["particles/system"] = np.array([0, 0, 1, 1], np.int32)     # a batch
    arrays["particles/sample_index"] = np.array([1, 0, 0, 1], np.int32)  # renumbered
    path = tmp_path / "prepared.h5"
    io.save_checkpoint(path, arrays, {"time": 2.5, "walls": []})
    written = export.export(path, tmp_path / "vtk", parts=["particles", "contacts"])
    m = meshio.read(tmp_path / "vtk" / "prepared_particles_000000.vtu")
    np.testing.assert_array_equal(m.points, f["particles/x"])
    np.testing.assert_array_equal(m.point_data["system"], [0, 0, 1, 1])
    np.testing.assert_array_equal(m.point_data["sample_index"], [1, 0, 0, 1])
    np.testing.assert_array_equal(m.point_data["id"], np.arange(4))
    root = ET.parse(written[-2]).getroot()
    assert [float(d.get("timestep")) for d in root.iter("DataSet")] == [2.5]
    with pytest.raises(ValueError, match="one state"):
        export.export(path, tmp_path / "vtk", frames=[1])
    # 0 and -1 are both its frame (refused together before session 72; render took them)
    assert export.load_states(path, [0, -1])[0][0]["index"] == 0
    with pytest.raises(ValueError, match="one state"):
        export.export(path, tmp_path / "vtk", frames=[0, 1])


def test_bad_requests_are_refused_with_the_problem_named(states, tmp_path, capsys):
    with pytest.raises(ValueError, match="frame index 5 out of range \\(2 frames\\)"):
        export.export(states, tmp_path / "vtk", frames=[5])
    with pytest.raises(ValueError, match="parts spheres"):
        export.export(states, tmp_path / "vtk", parts=["spheres"])
    series = tmp_path / "series.h5"
    io.write_series(series, {"time": np.arange(3.0)})
    with pytest.raises(ValueError, match="series file holds no particle states"):
        export.export(series, tmp_path / "vtk")
    with pytest.raises(FileNotFoundError):
        export.export(tmp_path / "missing.h5", tmp_path / "vtk")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="not a directory"):
        export.export(states, tmp_path / "file")
    # io refuses to write such indices; a file edited by hand may still hold them: the frame
    # is checked when it is read, whatever part is exported
    import h5py
    for key, value, message in (
            ("bonds/j", 4, r"frame 0: key 'bonds/j' has indices in \[3, 4\], expected \[0, 4\)"),
            ("contacts/j", 6, r"frame 0: key 'contacts/j' has indices in \[\d, 6\], "
                              r"expected \[0, 6\) with N=4, W=2"),
            ("particles/radius", -1.0, "1 radii that are not positive and finite")):
        bad = tmp_path / f"bad_{key.replace('/', '_')}.h5"
        io.append_frame(bad, frame(), time=0.0, step=0, stage="x")
        with h5py.File(bad, "a") as f:
            f[f"frames/000000/{key}"][1] = value     # a bond to body 4 (a wall), wall 2 of 2, ...
        for part in ("particles", "bonds"):
            with pytest.raises(ValueError, match=message):
                export.export(bad, tmp_path / "vtk2", parts=[part])
    assert not (tmp_path / "vtk2").exists()
    # a frame of a run that diverged is exported (to be looked at), and named
    bad = tmp_path / "diverged.h5"
    for k in range(3):
        f = frame(shift=0.001 * k)
        if k == 1:
            f["particles/x"][2] = np.nan
        io.append_frame(bad, f, time=0.1 * k, step=k, stage="x")
    written = export.export(bad, tmp_path / "vtk3", parts=["particles"])
    assert len(written) == 4
    assert "1 frame(s) hold positions that are not finite (a run that diverged?): 1" in \
        capsys.readouterr().err


def test_an_interrupted_export_leaves_the_previous_files_whole(states, tmp_path, monkeypatch):
    out = tmp_path / "vtk"
    export.export(states, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    calls = {"n": 0}
    real = meshio.write

    def failing(path, mesh, **kw):
        calls["n"] += 1
        if calls["n"] == 3:
            real(path, mesh, **kw)      # a partial file in the temporary path, then a crash
            raise KeyboardInterrupt
        return real(path, mesh, **kw)

    monkeypatch.setattr(meshio, "write", failing)
    with pytest.raises(KeyboardInterrupt):
        export.export(states, out, frames=[1, 0])
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert set(after) == set(before)            # no temporary file left behind
    for name in ("states_particles.pvd", "states_bonds_000000.vtu", "states_walls_000000.vtu"):
        assert after[name] == before[name]


def test_cli_export(states, tmp_path, capsys):
    assert cli.main(["export", str(states), "--out", str(tmp_path / "vtk"), "--frames", "-1",
                     "--parts", "particles,bonds"]) == 0
    out = capsys.readouterr().out
    assert "wrote 2 VTK files" in out and "states_particles.pvd" in out
    assert sorted(p.name for p in (tmp_path / "vtk").iterdir()) == [
        "states_bonds.pvd", "states_bonds_000001.vtu",
        "states_particles.pvd", "states_particles_000001.vtu"]
    assert cli.main(["export", str(states), "--out", str(tmp_path / "v"), "--parts", "x"]) == 2
    assert cli.main(["export", str(tmp_path / "none.h5"), "--out", str(tmp_path / "v")]) == 2
    assert "none.h5: no such file" in capsys.readouterr().err


def test_an_export_of_another_file_of_the_same_name_is_refused_not_mixed(states, tmp_path,
                                                                          capsys):
    """Every sample's snapshots are a states.h5: exporting a second sample into the folder of
    the first replaced the first's frames one by one and mixed the rest under one name, with
    no word (session 72's review). Now each .pvd names its source, another source is refused
    before anything is written, and --prefix names an export; a folder where a file goes is
    refused before the first file too (all .vtu files and three .pvd files were written)."""
    other = tmp_path / "other" / "states.h5"
    other.parent.mkdir()
    io.append_frame(other, frame(0.002), time=0.5, step=10, stage="prepare",
                    scenario_text=SCENARIO)
    out = tmp_path / "vtk"
    export.export(states, out)
    assert export.exported_from(out / "states_particles.pvd") == str(states.resolve())
    ET.parse(out / "states_particles.pvd")                  # still plain VTK XML
    before = {q.name: q.read_bytes() for q in out.iterdir()}
    assert cli.main(["export", str(other), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"holds an export of {states.resolve()}" in err and "--prefix" in err, err
    assert {q.name: q.read_bytes() for q in out.iterdir()} == before
    export.export(states, out, frames=[0])                  # the same file again: its own
    assert cli.main(["export", str(other), "--out", str(out), "--prefix", "other"]) == 0
    assert export.exported_from(out / "other_walls.pvd") == str(other.resolve())
    m = meshio.read(out / "other_particles_000000.vtu")
    assert np.allclose(m.points, frame(0.002)["particles/x"])
    assert cli.main(["export", str(other), "--out", str(out), "--prefix", "a/b"]) == 2
    assert "--prefix 'a/b': expected a file name prefix" in capsys.readouterr().err
    fresh = tmp_path / "fresh"
    (fresh / "states_walls.pvd").mkdir(parents=True)
    assert cli.main(["export", str(states), "--out", str(fresh)]) == 2
    assert "states_walls.pvd: is a directory" in capsys.readouterr().err
    assert [q.name for q in fresh.iterdir()] == ["states_walls.pvd"]


# --- session 43's mutation audit of the files and checks that guard the results -------------
# export.py load_states: a checkpoint's contact arrays past its `contacts/start` table's end are
# unused capacity, not contacts
def test_a_checkpoint_s_unused_contact_capacity_is_not_exported(tmp_path):
    import meshio
    from tcd import export
    x = np.array([[0.0, 0, 0.01], [0.02, 0, 0.01], [0.04, 0, 0.01]])
    arrays = {"particles/x": x, "particles/radius": np.full(3, 0.01),
              # two contacts (0-1, 1-2), then two slots of unused capacity
              "contacts/start": np.array([0, 1, 2, 2], np.int32),
              "contacts/i": np.array([0, 1, 0, 0], np.int32),
              "contacts/j": np.array([1, 2, 0, 0], np.int32),
              "contacts/impulse": np.zeros((4, 3)), "contacts/gap": np.zeros(4)}
    path = tmp_path / "checkpoint.h5"
    io.save_checkpoint(path, arrays, {"time": 1.0})
    (state,), _ = export.load_states(path)
    np.testing.assert_array_equal(state["contacts/i"], [0, 1])
    np.testing.assert_array_equal(state["contacts/j"], [1, 2])
    export.export(path, tmp_path / "vtk", parts=["contacts"])
    m = meshio.read(tmp_path / "vtk" / "checkpoint_contacts_000000.vtu")
    np.testing.assert_array_equal(m.cells_dict["line"], [[0, 1], [1, 2]])

