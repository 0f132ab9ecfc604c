"""`tcd analyse`: contact network, fabric and Love-Weber grain stress of snapshots, checked on
configurations whose forces are known in closed form."""
import csv
import json
import math
import pathlib

import numpy as np
import pytest

from tcd import analysis, cli, io

H = 2e-4
G = 9.81
SCENARIO = f'name = "t"\n[solver]\ntime_step = {H}\n'


def walls():
    return {"walls/kind": np.array([io.WALL_PLANE, io.WALL_CYLINDER], np.int32),
            "walls/point": np.zeros((2, 3)),
            "walls/direction": np.array([[0, 0, 1.0], [0, 0, 1.0]]),
            "walls/radius": np.array([0.05, 0.05]),
            "walls/extent": np.array([[0.0, 0.0], [0.0, 0.2]]),
            "walls/force": np.zeros((2, 3))}


def column(k=4, r=0.005, rho=2600.0):
    """k spheres stacked on the floor at rest: contact (s, s+1) carries the weight of the k-1-s
    spheres above s, the floor carries all k."""
    m = rho * 4 / 3 * math.pi * r**3
    x = np.zeros((k, 3))
    x[:, 2] = r + 2 * r * np.arange(k)
    i = list(range(k - 1)) + [0]
    j = list(range(1, k)) + [k]                      # k = N + 0: the floor
    imp = [[0, 0, (k - 1 - s) * m * G * H] for s in range(k - 1)] + [[0, 0, -k * m * G * H]]
    f = {"particles/x": x, "particles/radius": np.full(k, r),
         "contacts/i": np.array(i, np.int32), "contacts/j": np.array(j, np.int32),
         "contacts/impulse": np.array(imp, float), **walls()}
    return f, m


def per_grain_stress(frame, contact_points, h):
    """Oracle: sum over grains and their contacts of (x_c - x_p) (x) f_c->p / sum V_p, with the
    contact points given explicitly."""
    x, r = frame["particles/x"], frame["particles/radius"]
    n = len(x)
    s = np.zeros((3, 3))
    for (i, j, imp), xc in zip(zip(frame["contacts/i"], frame["contacts/j"],
                                   frame["contacts/impulse"]), contact_points):
        s += np.outer(xc - x[i], -imp / h)
        if j < n:
            s += np.outer(xc - x[j], imp / h)
    return s / np.sum(4 / 3 * math.pi * r**3)


def test_stress_of_a_column_at_rest_is_its_weight():
    k, r = 4, 0.005
    f, m = column(k, r)
    s = analysis.grain_stress(f, H)
    # closed form: -r m g k^2 over the grains' volume k 4/3 pi r^3
    assert s[2, 2] == pytest.approx(-3 * m * G * k / (4 * math.pi * r**2), rel=1e-12)
    assert np.max(np.abs(s - np.diag(np.diag(s)))) == 0.0 and s[0, 0] == s[1, 1] == 0.0
    points = [f["particles/x"][q] + [0, 0, r] for q in range(k - 1)] + [f["particles/x"][0] - [0, 0, r]]
    np.testing.assert_allclose(s, per_grain_stress(f, points, H), rtol=1e-12, atol=1e-9)


def test_a_grain_pressed_on_the_mould_stresses_it_radially():
    r, R, P = 0.005, 0.05, 3.0
    f = {"particles/x": np.array([[0.0, R - r, 0.05]]), "particles/radius": np.array([r]),
         "contacts/i": np.array([0], np.int32), "contacts/j": np.array([2], np.int32),   # wall 1
         "contacts/impulse": np.array([[0.0, P * H, 0.0]]), **walls()}
    s = analysis.grain_stress(f, H)
    V = 4 / 3 * math.pi * r**3
    assert s[1, 1] == pytest.approx(-r * P / V, rel=1e-12)
    np.testing.assert_allclose(s, per_grain_stress(f, [np.array([0.0, R, 0.05])], H), rtol=1e-12)


def test_an_intact_bond_in_tension_gives_positive_stress_and_a_broken_one_none():
    r, T = 0.004, 5.0
    f = {"particles/x": np.array([[0.0, 0, 0.1], [2 * r, 0, 0.1]]),
         "particles/radius": np.array([r, r]),
         "bonds/i": np.array([0, 0], np.int32), "bonds/j": np.array([1, 1], np.int32),
         "bonds/state": np.array([io.BOND_INTACT, io.BOND_BROKEN_SHEAR], np.int8),
         "bonds/impulse": np.array([[-T * H, 0, 0], [-100.0, 0, 0]]), **walls()}
    s = analysis.grain_stress(f, H)
    assert s[0, 0] == pytest.approx(2 * r * T / (2 * 4 / 3 * math.pi * r**3), rel=1e-12)
    row = analysis.frame_row({**f, "time": 0.0, "step": 0}, H)
    assert row["bonds_intact"] == 1 and row["bonds_broken"] == 1
    assert row["coordination_bonds"] == pytest.approx(1.0)
    assert row["fabric_xx"] == pytest.approx(1.0) and row["fabric_anisotropy"] == pytest.approx(1.0)


def test_fabric_of_an_isotropic_network_and_the_counts():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0],
                  [0, 0, -1]], float) * 0.01
    f = {"particles/x": x, "particles/radius": np.full(7, 0.005),
         "contacts/i": np.array([0] * 6 + [3], np.int32),
         "contacts/j": np.array([1, 2, 3, 4, 5, 6, 7], np.int32),     # the last with the floor
         "contacts/impulse": np.array([[1e-3, 0, 0], [0, 1e-3, 0], [0, 0, 1e-3], [-1e-3, 0, 0],
                                       [0, -1e-3, 0], [0, 0, -3e-3], [0, 0, 0]]),
         **walls(), "time": 1.5, "step": 3}
    row = analysis.frame_row(f, H)
    for c in ("xx", "yy", "zz"):
        assert row[f"fabric_{c}"] == pytest.approx(1 / 3)
    for c in ("yz", "xz", "xy"):
        assert row[f"fabric_{c}"] == pytest.approx(0.0, abs=1e-15)
    assert row["fabric_anisotropy"] == pytest.approx(0.0, abs=1e-12)
    assert (row["contacts"], row["wall_contacts"]) == (6, 1)
    assert row["coordination_contacts"] == pytest.approx(12 / 7)
    assert row["coordination_contacts_force_carrying"] == pytest.approx(12 / 7)   # all pressed
    # forces (R.n / H, n from i to j): five pairs pressed at 5 N, the one below (j = 6, at -z,
    # R = -3e-3 z) at 15 N
    assert row["normal_force_mean"] == pytest.approx((5 * 5.0 + 15.0) / 6)
    assert row["normal_force_max"] == pytest.approx(15.0)


def test_a_pair_listed_as_contact_and_intact_bond_counts_once():
    """The frame written as the bonds are made still lists every bonded pair as a contact (the
    solver takes a bonded pair as its bond from the next step): counted twice, the fabric of
    the tiny scenario's first shear frame was 3.5 % too anisotropic and its contacts 331 for
    the 34 that stayed (session 44's audit). A bonded pair counts as a bond only; a broken
    bond's pair listed as a contact is a contact."""
    x = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01]], float)
    f = {"particles/x": x, "particles/radius": np.full(4, 0.005),
         "contacts/i": np.array([0, 0, 0], np.int32), "contacts/j": np.array([1, 2, 3], np.int32),
         "contacts/impulse": np.zeros((3, 3)),
         "bonds/i": np.array([1, 0], np.int32), "bonds/j": np.array([0, 2], np.int32),
         "bonds/state": np.array([io.BOND_INTACT, io.BOND_INTACT + 1], np.int8),
         "bonds/impulse": np.zeros((2, 3)), **walls(), "time": 0.0, "step": 0}
    row = analysis.frame_row(f, H)
    # pairs: (0, 1) bonded (listed twice, counted once), (0, 2) broken bond + contact, (0, 3)
    assert (row["contacts"], row["bonds_intact"], row["bonds_broken"]) == (2, 1, 1)
    assert row["coordination_contacts"] == pytest.approx(2 * 2 / 4)
    for c in ("xx", "yy", "zz"):
        assert row[f"fabric_{c}"] == pytest.approx(1 / 3)


def test_series_files_one_row_per_frame(tmp_path):
    f, m = column()
    path = tmp_path / "states.h5"
    io.append_frame(path, f, time=0.1, step=5, stage="prepare", scenario_text=SCENARIO)
    g = dict(f)
    g["contacts/impulse"] = 2 * f["contacts/impulse"]
    io.append_frame(path, g, time=0.2, step=10, stage="shear")
    h5, csv_path = analysis.analyse(path, tmp_path / "micro")
    series = io.read_series(h5)
    np.testing.assert_array_equal(series["frame"], [0, 1])
    np.testing.assert_array_equal(series["time"], [0.1, 0.2])
    assert series["stress_zz"][1] == pytest.approx(2 * series["stress_zz"][0], rel=1e-12)
    assert series["stress_zz"][0] == pytest.approx(-3 * m * G * 4 / (4 * math.pi * 0.005**2))
    with open(csv_path) as fh:
        rows = list(csv.reader(fh))
    assert rows[0][:3] == ["frame [1]", "time [s]", "step [1]"] and "stress_zz [Pa]" in rows[0]
    assert len(rows) == 3


def test_checkpoint_needs_a_time_step_for_forces(tmp_path):
    f, _ = column()
    path = tmp_path / "prepared.h5"
    io.save_checkpoint(path, f, {"time": 1.0})
    h5, _ = analysis.analyse(path, tmp_path / "a")
    assert "stress_zz" not in io.read_series(h5) and "fabric_zz" in io.read_series(h5)
    h5, _ = analysis.analyse(path, tmp_path / "b", time_step=H)
    assert io.read_series(h5)["stress_zz"][0] < 0
    with pytest.raises(ValueError, match="time step -1"):
        analysis.analyse(path, tmp_path / "c", time_step=-1.0)
    with pytest.raises(ValueError, match="does not exist"):
        analysis.analyse(path, tmp_path / "nowhere" / "c")


def test_cli_analyse(tmp_path, capsys):
    f, _ = column()
    path = tmp_path / "prepared.h5"
    io.save_checkpoint(path, f, {"time": 1.0})
    assert cli.main(["analyse", str(path), "--out", str(tmp_path / "m"), "--time-step", "2e-4"]) == 0
    assert "m.csv" in capsys.readouterr().out
    assert cli.main(["analyse", str(path), "--out", str(tmp_path / "m"), "--time-step", "0"]) == 2
    assert cli.main(["analyse", str(tmp_path / "x.h5"), "--out", str(tmp_path / "m")]) == 2
    # an earlier analysis is replaced (above); a run's series is not, nor an empty prefix
    # (session 42 audit: it replaced a run's shear_series.h5 and .csv, and wrote ".h5")
    capsys.readouterr()
    io.write_series(tmp_path / "shear_series.h5", {"time": np.arange(3.0)},
                    csv_path=tmp_path / "shear_series.csv")
    before = (tmp_path / "shear_series.h5").read_bytes()
    assert cli.main(["analyse", str(path), "--out", str(tmp_path / "shear_series"),
                     "--time-step", "2e-4"]) == 2
    assert "shear_series.h5 exists and is not an output of tcd analyse" in capsys.readouterr().err
    assert (tmp_path / "shear_series.h5").read_bytes() == before
    (tmp_path / "shear_series.h5").unlink()
    assert cli.main(["analyse", str(path), "--out", str(tmp_path / "shear_series"),
                     "--time-step", "2e-4"]) == 2           # its CSV twin alone is kept too
    assert cli.main(["analyse", str(path), "--out", str(tmp_path) + "/", "--time-step", "2e-4"]) == 2
    assert "give a file name prefix" in capsys.readouterr().err


def test_the_shipped_sample_at_rest_obeys_the_virial_theorem():
    """At rest, with a floor, a frictionless mould and a top plate that barely touches, the
    contacts' vertical moment balances gravity's: sigma_zz = -rho g z_G (z_G: the grains'
    centre of mass), the other terms carry no vertical force."""
    path = pathlib.Path(__file__).resolve().parents[1] / "samples" / "leutner_seed1_prepared.h5"
    states, _ = analysis.load_states(path)
    f = states[0]
    assert abs(f["walls/force"][2, 2]) < 1e-6        # the top plate
    s = analysis.grain_stress(f, 2e-4)               # the preparation's time step
    x, r = f["particles/x"], f["particles/radius"]
    z_g = float(np.sum(r**3 * x[:, 2]) / np.sum(r**3))
    assert s[2, 2] == pytest.approx(-2600.0 * 9.81 * z_g, rel=1e-3)


def test_a_time_step_that_contradicts_the_file_is_refused(tmp_path):
    """A states file records the step its impulses were computed with: another --time-step
    would scale every force wrongly; the same one is accepted."""
    f, _ = column()
    path = tmp_path / "states.h5"
    io.append_frame(path, f, time=0.1, step=5, stage="prepare", scenario_text=SCENARIO)
    with pytest.raises(ValueError, match="records its own time step"):
        analysis.analyse(path, tmp_path / "a", time_step=2 * H)
    analysis.analyse(path, tmp_path / "b", time_step=H)


def test_a_checkpoint_gives_the_time_step_of_its_scenario(tmp_path, capsys):
    """A run's checkpoint (or prepared sample) keeps its scenario, and with it the time step its
    impulses were computed with: it was taken as unknown, so `tcd analyse` left the stresses
    out and took any --time-step, giving every stress scaled by the wrong step (session 72's
    review). Now it gives the same stresses as a states file of that scenario."""
    f, _ = column()
    states, ck = tmp_path / "states.h5", tmp_path / "checkpoint.h5"
    io.append_frame(states, f, time=0.1, step=5, stage="prepare", scenario_text=SCENARIO)
    io.save_checkpoint(ck, f, {"time": 0.1, "step": 5, "scenario_text": SCENARIO})
    assert analysis.load_states(ck)[1] == H
    a = io.read_series(analysis.analyse(states, tmp_path / "a")[0])
    b = io.read_series(analysis.analyse(ck, tmp_path / "b")[0])
    assert b["stress_zz"][0] < 0 and b["stress_zz"][0] == a["stress_zz"][0]
    with pytest.raises(ValueError, match="records its own time step"):
        analysis.analyse(ck, tmp_path / "c", time_step=2 * H)
    # with no scenario in its meta the step is unknown, and --time-step gives it
    io.save_checkpoint(ck, f, {"time": 0.1})
    assert "stress_zz" not in io.read_series(analysis.analyse(ck, tmp_path / "d")[0])
    assert "does not give the time step" in capsys.readouterr().err
    d = io.read_series(analysis.analyse(ck, tmp_path / "e", time_step=H)[0])
    assert d["stress_zz"][0] == a["stress_zz"][0]


def test_the_frames_of_a_branched_states_file_use_each_its_own_time_step(tmp_path):
    """`tcd run --from` at another time step records, in the states file, the step of the
    frames from the branch on (`time_steps`); the frames before keep theirs."""
    import h5py
    f, _ = column()
    path = tmp_path / "states.h5"
    for k in range(3):
        io.append_frame(path, f, time=0.1 * k, step=k, stage="prepare", scenario_text=SCENARIO)
    with h5py.File(path, "a") as g:
        g.attrs["time_steps"] = json.dumps([[0, H], [2, H / 2]])
    states, h = analysis.load_states(path)
    assert h is None and [s["time_step"] for s in states] == [H, H, H / 2]
    rows = io.read_series(analysis.analyse(path, tmp_path / "a")[0])["stress_zz"]
    assert rows[2] == pytest.approx(2 * rows[0], rel=1e-12) and rows[0] == rows[1] < 0
    with pytest.raises(ValueError, match="0.0001 and 0.0002 s"):
        analysis.analyse(path, tmp_path / "b", time_step=H)
    with h5py.File(path, "a") as g:
        g.attrs["time_steps"] = "[[0, -1]]"
    with pytest.raises(ValueError, match="time_steps attribute"):
        analysis.load_states(path)


# --- session 43's mutation audit of the files and checks that guard the results -------------
# analysis.py frame_row: fabric_anisotropy is the largest minus the smallest eigenvalue
def test_fabric_anisotropy_is_largest_minus_smallest_eigenvalue():
    from tcd import analysis
    x = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1]], float) * 0.01
    f = {"particles/x": x, "particles/radius": np.full(4, 0.005),
         "contacts/i": np.array([0, 0, 0], np.int32), "contacts/j": np.array([1, 2, 3], np.int32),
         "contacts/impulse": np.zeros((3, 3)), "time": 0.0, "step": 0}
    row = analysis.frame_row(f, None)
    assert (row["fabric_xx"], row["fabric_yy"], row["fabric_zz"]) == pytest.approx((2 / 3, 0, 1 / 3))
    assert row["fabric_anisotropy"] == pytest.approx(2 / 3)

